"""Request (``*Create`` / ``*Request``) and response (``*Public``) bodies of the learner service."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, ValidationInfo, field_validator

from services.core.feedback import LabelChannel, is_error
from services.core.hf_methods import HFMethodName
from services.core.model_formats import ModelFormat
from services.core.schemas import ActionValue, Seed, StrictRequest
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.sim.env import OBS_SIZE

Observation = Annotated[
    list[Annotated[float, Field(strict=True)]],  # JSON numbers only: no "1" or true
    Field(
        min_length=OBS_SIZE,
        max_length=OBS_SIZE,
        description=f"The env's {OBS_SIZE} finite floats (10 ray distances, goal distance, "
        "goal angle, heading), unnormalised, each within the env's observation space on the "
        "session's map (422 naming the element otherwise).",
    ),
]


class FhatSettings(StrictRequest):
    """Overrides of Fhat's settings (:class:`services.learner.feedback.FeedbackConfig`).

    Omitted fields keep the paper's values.
    """

    hidden_size: int | None = Field(None, strict=True, ge=1, le=1024, description="Paper: 16.")
    lr: float | None = Field(None, gt=0, le=1, description="Adam learning rate (1e-3).")
    replay_updates: int | None = Field(
        None, strict=True, ge=0, le=1000, description="K_HF: replay steps per label (16)."
    )
    batch_size: int | None = Field(None, strict=True, ge=1, le=4096, description="(32)")
    newest_fraction: float | None = Field(
        None, ge=0, le=1, description="Chance a replay batch is the newest labels (0.3)."
    )
    validation_fraction: float | None = Field(
        None, ge=0, lt=1, description="Chance a label is held out for validation (0.2)."
    )
    beta: float | None = Field(
        None, gt=0, le=1000, description="Inverse temperature of pi_HF's sampling (8)."
    )
    good_accuracy: float | None = Field(
        None,
        gt=0,
        le=1,
        description="Label-noise model: the classifier's accuracy on "
        "correct actions (its calibration recall); 0.6 assumed when omitted.",
    )
    bad_accuracy: float | None = Field(
        None,
        gt=0,
        le=1,
        description="Label-noise model: the classifier's accuracy on "
        "erroneous actions; 0.6 assumed when omitted.",
    )
    kernel_bandwidth: float | None = Field(
        None,
        gt=0,
        le=10,
        description="categorical_kernel only: width of the kernel that shares a label's "
        "evidence with nearby states, on the normalised observation (0.1).",
    )

    label_channel: LabelChannel | None = Field(
        None,
        description="How a label enters Fhat: 'hard', the thresholded feedback under the "
        "label-noise model (the paper); 'soft', the classifier's calibrated "
        "log_likelihood_ratio, which every label must then carry ('hard' when omitted).",
    )

    def overrides(self) -> dict[str, Any]:
        """The fields given."""
        return {k: v for k, v in self.model_dump().items() if v is not None}


class HFSessionCreate(StrictRequest):
    """Start an online HF-training session (stage 2 of the paper, label by label)."""

    task: Literal["sssg", "vssg"] = Field(
        "sssg", description="sssg: single start single goal; vssg: start jittered."
    )
    map: str | None = Field(
        None,
        max_length=1024,
        description="Name (e.g. 'default') or path of a map the service ships or is "
        "configured with (the sim service's maps); default map when omitted.",
    )
    seed: Seed = Field(
        0,
        description="Run seed: Fhat's initial weights, the validation split and pi_HF's "
        "sampling are those of `bgrl reproduce`'s stage 2 for this seed.",
    )
    label_budget: int = Field(1000, strict=True, ge=1, description="Labels to collect.")
    method: HFMethodName = Field(
        RECOMMENDED_METHOD,
        description="Stage-2 method: how Fhat is trained and which actions are labelled "
        "(docs/stage2.md); 'paper' is the paper's Fhat, the default is the platform's "
        "recommended method.",
    )
    fhat: FhatSettings = Field(default_factory=FhatSettings)


class HFSessionPublic(BaseModel):
    """An HF session and its current state."""

    id: str
    task: str
    map: str
    seed: int
    method: str
    fhat: dict[str, Any] = Field(description="Fhat's settings in use.")
    label_budget: int
    labels: int = Field(description="Labels received (training and validation).")
    model_version: int = Field(description="Training labels Fhat was updated with.")
    metrics: dict[str, Any]
    done: bool = Field(description="True once the label budget is reached.")
    created_at: datetime


class ActRequest(StrictRequest):
    """Ask pi_HF for the action in a state."""

    observation: Observation
    greedy: bool = Field(
        False,
        strict=True,
        description="False: sample softmax(beta * sigmoid(Fhat)), as while collecting labels; "
        "true: argmax (the pi_HF that guides RL).",
    )


class ActPublic(BaseModel):
    """pi_HF's action."""

    action: int
    model_version: int
    greedy: bool


class LabelCreate(StrictRequest):
    """The decoded feedback on one executed action."""

    marker_id: str = Field(
        min_length=1,
        max_length=200,
        description="Unique per action (e.g. '<sim session>:<step>'); a label sent again "
        "with the same marker id is not counted twice.",
    )
    observation: Observation = Field(description="The state the action was taken in.")
    action: ActionValue
    feedback: Literal["correct", "error"]
    p_error: float | None = Field(
        None, ge=0, le=1, description="The classifier's P(error), when decoded from EEG."
    )
    log_likelihood_ratio: float | None = Field(
        None,
        ge=-1e4,
        le=1e4,
        description="log P(epoch | error) / P(epoch | correct) from the classifier's "
        "calibrated posterior (the EEG service's decision carries it): the soft label, "
        "required by a session on the soft channel, recorded by one on the hard channel.",
    )
    oracle_correct: bool | None = Field(
        None, strict=True, description="The oracle's truth, when known (simulation)."
    )
    next_observation: Observation | None = Field(
        None,
        description="The state the next action will be taken in: the answer then carries "
        "pi_HF's sampled action there, from the updated Fhat (one round trip instead of a "
        "label and a POST /act).",
    )

    @field_validator("p_error")
    @classmethod
    def _p_error_matches_feedback(cls, p_error: float | None, info: ValidationInfo) -> float | None:
        feedback = info.data.get("feedback")
        if (
            p_error is not None
            and feedback is not None
            and is_error(p_error) != (feedback == "error")
        ):
            decoded = "error" if is_error(p_error) else "correct"
            raise ValueError(f"p_error {p_error:g} decodes to {decoded}, not {feedback}")
        return p_error


class LabelPublic(BaseModel):
    """The session after a label."""

    labels: int
    model_version: int
    metrics: dict[str, Any]
    done: bool
    duplicate: bool = Field(description="The marker id was labelled before; nothing changed.")
    validation: bool = Field(description="The label was held out for validation.")
    next_action: int | None = Field(
        None,
        description="pi_HF's sampled action in next_observation (as POST /act answers), "
        "when it was given and the budget is not full.",
    )
    prepared: bool = Field(
        False,
        description="The label had been prepared (POST /labels/prepare): its update was "
        "computed in advance and swapped in.",
    )


class LabelPrepare(StrictRequest):
    """A label whose feedback is not known yet: its update is computed for both values."""

    marker_id: str = Field(min_length=1, max_length=200, description="As in the label.")
    observation: Observation = Field(description="The state the action was taken in.")
    action: ActionValue
    oracle_correct: bool | None = Field(
        None, strict=True, description="The oracle's truth, when known (simulation)."
    )
    next_observation: Observation | None = Field(
        None, description="The label's next_observation (pi_HF's next action is sampled there)."
    )


class LabelPreparePublic(BaseModel):
    """Whether a label was prepared."""

    prepared: bool = Field(
        description="False for a marker labelled before or a full budget (the label then "
        "takes the ordinary path)."
    )


class ExportRequest(StrictRequest):
    """Export the greedy pi_HF (no options yet: an empty object)."""


class ExportedFile(BaseModel):
    """One file of an exported pi_HF in the platform's artifact store."""

    relpath: str
    sha256: str
    size_bytes: int


class ExportPublic(BaseModel):
    """Where the pi_HF was stored in the platform's artifact store, one file a format
    (``torchscript``, ``pt2``, ``onnx``)."""

    files: dict[ModelFormat, ExportedFile]
    model_version: int
    metrics: dict[str, Any]
