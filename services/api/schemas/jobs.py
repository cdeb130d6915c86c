"""Schemas of jobs and of each kind's ``config`` (checked before a job is queued).

The learner cannot be imported here (the api stays free of torch), so what a job config
takes from it is listed below: the PPO settings a job may override with their types and
bounds (the fields of ``services.learner.ppo.PPOConfig`` that ``bgrl reproduce --ppo``
accepts) and the presets of ``bgrl reproduce --preset`` (``services.learner.specs.PRESETS``);
the stage-2 method names come from :mod:`services.core.hf_methods`. Tests check that each
list equals the learner's.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationInfo, field_validator, model_validator

from services.api.schemas.common import MAX_ROW_ID, ApiRequest, PublicModel
from services.core.db.models import JOB_STATUSES
from services.core.hf_methods import HFMethodName

JobKind = Literal["guided_ppo", "reproduce", "eeg_calibration", "bids_export", "session_replay"]
"""Kinds a user may submit (``reproduce_run`` jobs are created by a reproduce job)."""
JobListKind = Literal[
    "guided_ppo",
    "reproduce",
    "eeg_calibration",
    "bids_export",
    "session_replay",
    "reproduce_run",
    "live_session",
]
"""Kinds the job list filters on: the submitted kinds, a reproduce job's runs and the live
sessions' runs (started from a session, not submitted)."""
assert set(JobListKind.__args__) == {*JobKind.__args__, "reproduce_run", "live_session"}  # type: ignore[attr-defined]
JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
assert set(JobStatus.__args__) == set(JOB_STATUSES)  # type: ignore[attr-defined]

Task = Literal["sssg", "vssg"]
Method = Literal["rl_sparse", "rl_rich", "rl_shaped", "hf_sparse"]
Treatment = Literal["authors", "truncated_is"]
Preset = Literal["paper", "platform"]
"""Settings of a reproduction (``bgrl reproduce --preset``); the learner's ``PRESETS``."""
PRESETS: tuple[str, ...] = Preset.__args__  # type: ignore[attr-defined]
MAX_TOTAL_STEPS = 2_000_000
MAX_REPRODUCE_RUNS = 2000
PPO_DEFAULT_N_STEPS = 128
PPO_DEFAULT_MINIBATCH_SIZE = 64


def _task(value: object) -> object:
    return value.lower() if isinstance(value, str) else value


class PPOOverrides(ApiRequest):
    """PPO settings to change (``bgrl reproduce --ppo KEY=VALUE``); omitted ones keep defaults.

    ``env_id``, ``env_kwargs``, ``seed``, ``eval_seeds`` and ``hf_treatment`` are set per run
    and cannot be overridden.
    """

    total_steps: int | None = Field(None, ge=1, le=MAX_TOTAL_STEPS)
    n_steps: int | None = Field(None, ge=1, le=100_000)
    n_epochs: int | None = Field(None, ge=1, le=1000)
    minibatch_size: int | None = Field(None, ge=1, le=100_000)
    learning_rate: float | None = Field(None, gt=0, le=1)
    anneal_lr: bool | None = None
    adam_eps: float | None = Field(None, gt=0, le=1)
    gamma: float | None = Field(None, ge=0, le=1)
    gae_lambda: float | None = Field(None, ge=0, le=1)
    clip_coef: float | None = Field(None, gt=0, le=10)
    ent_coef: float | None = Field(None, ge=0, le=10)
    vf_coef: float | None = Field(None, ge=0, le=100)
    max_grad_norm: float | None = Field(None, gt=0, le=1e6)
    target_kl: float | None = Field(None, gt=0, le=10)
    norm_adv: bool | None = None
    reward_scale: float | None = Field(None, gt=0, le=1e6)
    hidden_sizes: list[int] | None = Field(None, min_length=1, max_length=8)
    eval_every: int | None = Field(None, ge=1, le=MAX_TOTAL_STEPS)
    hf_eps_init: float | None = Field(None, ge=0, le=1)
    hf_t_trans_fraction: float | None = Field(None, gt=0, le=1)
    hf_warmup_steps: int | None = Field(None, ge=0, le=MAX_TOTAL_STEPS)
    is_clip: float | None = Field(None, gt=0, le=100)
    hf_guide_sampling: bool | None = None
    hf_prior_coef: float | None = Field(None, ge=0, le=100)
    hf_handover_on_revisit: bool | None = None
    hf_hold_until_success: bool | None = None
    hf_withdraw_after: int | None = Field(None, ge=0, le=MAX_TOTAL_STEPS)
    explore_coef: float | None = Field(None, ge=0, le=1e6)
    explore_cell_m: float | None = Field(None, gt=0, le=100)
    sil_coef: float | None = Field(None, ge=0, le=100)
    sil_updates: int | None = Field(None, ge=0, le=10_000)
    sil_value_coef: float | None = Field(None, ge=0, le=100)
    sil_capacity: int | None = Field(None, ge=1, le=10_000_000)

    @field_validator("hidden_sizes")
    @classmethod
    def _layer_sizes(cls, value: list[int] | None) -> list[int] | None:
        if value is not None and not all(1 <= size <= 4096 for size in value):
            raise ValueError("every hidden layer needs 1 to 4096 units")
        return value

    def given(self) -> dict[str, Any]:
        """Only the settings given."""
        return self.model_dump(exclude_none=True)

    def check_steps(self, total_steps: int) -> None:
        """PPOConfig's own rules: n_steps a multiple of minibatch_size, <= total_steps."""
        n_steps = self.n_steps or PPO_DEFAULT_N_STEPS
        minibatch = self.minibatch_size or PPO_DEFAULT_MINIBATCH_SIZE
        if n_steps % minibatch:
            raise ValueError(
                f"n_steps ({n_steps}) must be a multiple of minibatch_size ({minibatch})"
            )
        if total_steps < n_steps:
            raise ValueError(f"total_steps ({total_steps}) must be at least n_steps ({n_steps})")


class GuidedPPOConfig(ApiRequest):
    """One training run of (guided) PPO: ``bgrl`` learner's run of one task, method and seed."""

    task: Task = Field(description="SSSG or VSSG (case-insensitive).")
    method: Method
    accuracy: float | None = Field(
        None, ge=0, le=1, description="Simulated feedback accuracy C (hf_sparse only)."
    )
    seed: int = Field(0, ge=0, le=2**31 - 1)
    total_steps: int = Field(40_000, ge=1, le=MAX_TOTAL_STEPS)
    hf_treatment: Treatment = "authors"
    ppo: PPOOverrides = Field(default_factory=PPOOverrides)
    preset: Preset = Field(
        "paper",
        description="PPO settings: paper (the paper's) or platform (the recommended ones: "
        "hf_treatment 'authors' becomes 'truncated_is', ppo.hf_guide_sampling true and "
        "ppo.sil_coef 1 unless given). The stage-2 method is hf_method's either way.",
    )
    hf_model_id: int | None = Field(
        None,
        ge=1,
        le=MAX_ROW_ID,
        description="A stored pi_HF to guide with (hf_sparse) instead of training one.",
    )
    n_labels: int = Field(
        1000, ge=1, le=1_000_000, description="Feedback labels pi_HF is trained on (hf_sparse)."
    )
    hf_method: HFMethodName | None = Field(
        None,
        description="Stage-2 method that learns pi_HF (hf_sparse; docs/stage2.md); default "
        "the platform's recommended one, 'paper' the paper's Fhat.",
    )
    checkpoint_every: int | None = Field(
        None, ge=1, le=100_000, description="PPO updates between checkpoints (worker default)."
    )

    _lower_task = field_validator("task", mode="before")(_task)

    @field_validator("hf_method")
    @classmethod
    def _hf_method_for_hf_sparse(cls, value: str | None, info: ValidationInfo) -> str | None:
        method = info.data.get("method")
        if value is not None and method is not None and method != "hf_sparse":
            raise ValueError(f"hf_method applies to hf_sparse only, not {method}")
        if value is not None and info.data.get("hf_model_id") is not None:
            raise ValueError(
                "hf_method does not apply with hf_model_id: the stored pi_HF was learned "
                "with its own method"
            )
        return value

    @model_validator(mode="after")
    def _consistent(self) -> GuidedPPOConfig:
        if self.method == "hf_sparse":
            if self.accuracy is None and self.hf_model_id is None:
                raise ValueError("hf_sparse needs accuracy (or hf_model_id)")
        elif self.accuracy is not None or self.hf_model_id is not None:
            raise ValueError(f"accuracy and hf_model_id apply to hf_sparse only, not {self.method}")
        if self.ppo.total_steps is not None:
            raise ValueError("give total_steps in config.total_steps, not in config.ppo")
        self.ppo.check_steps(self.total_steps)
        return self


class ReproduceConfig(ApiRequest):
    """A reproduction of Fig. 3 (``bgrl reproduce`` options): one run per worker task.

    Not offered: ``--out`` (the results are the job's artifacts), ``--workers`` (the runs
    are spread over the Celery workers) and ``--map`` (a path on the api's host; workers run
    every job on the sim's default map).
    """

    quick: bool = Field(False, description="2 seeds (unless seeds is given).")
    seeds: int | None = Field(None, ge=1, le=100, description="Seeds per configuration.")
    first_seed: int = Field(0, ge=0, le=2**31 - 1)
    tasks: list[Task] = Field(default_factory=lambda: ["sssg", "vssg"], min_length=1)
    methods: list[Method] = Field(
        default_factory=lambda: ["rl_sparse", "rl_rich", "hf_sparse"], min_length=1
    )
    accuracies: list[float] = Field(default_factory=lambda: [0.55, 0.6, 0.7], min_length=1)
    treatments: list[Treatment] = Field(default_factory=lambda: ["authors"], min_length=1)
    ppo: PPOOverrides = Field(default_factory=PPOOverrides)
    preset: Preset = Field(
        "paper",
        description="paper: the paper's settings; platform: the recommended ones (treatments "
        "['authors'] become ['truncated_is'], ppo.hf_guide_sampling true and ppo.sil_coef 1 "
        "(self-imitation, every method alike) unless given, pi_HF learned with the "
        "recommended stage-2 method).",
    )
    checkpoint_every: int | None = Field(
        None, ge=1, le=100_000, description="PPO updates between checkpoints of each run."
    )
    n_labels: int = Field(
        1000, ge=1, le=1_000_000,
        description="Labels each hf_sparse run learns pi_HF from (every labelled action).",
    )  # fmt: skip

    @field_validator("tasks", mode="before")
    @classmethod
    def _lower_tasks(cls, value: object) -> object:
        return [_task(v) for v in value] if isinstance(value, list) else value

    @field_validator("tasks", "methods", "accuracies", "treatments")
    @classmethod
    def _distinct(cls, value: list[Any]) -> list[Any]:
        repeated = sorted({str(v) for v in value if value.count(v) > 1})
        if repeated:
            # a repeated entry would run (and count in the results) the same runs twice
            raise ValueError(f"each entry once: {', '.join(repeated)} repeated")
        return value

    @field_validator("accuracies")
    @classmethod
    def _accuracies(cls, value: list[float]) -> list[float]:
        if not all(0.0 <= c <= 1.0 for c in value):
            raise ValueError("every accuracy must be in [0, 1]")
        return value

    @model_validator(mode="after")
    def _resolved(self) -> ReproduceConfig:
        if self.seeds is None:
            self.seeds = 2 if self.quick else 10
        per_seed = sum(
            len(self.accuracies) * len(self.treatments) if m == "hf_sparse" else 1
            for m in self.methods
        ) * len(self.tasks)
        if per_seed * self.seeds > MAX_REPRODUCE_RUNS:
            raise ValueError(
                f"{per_seed * self.seeds} runs; a reproduce job may have {MAX_REPRODUCE_RUNS}"
            )
        self.ppo.check_steps(self.ppo.total_steps or 40_000)
        return self


class EEGCalibrationConfig(ApiRequest):
    """Train an ErrP classifier on a stored, valid recording."""

    recording_id: int = Field(ge=1, le=MAX_ROW_ID)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    max_passes: int | None = Field(
        None, ge=1, le=10_000, description="Training passes (default: the pipeline's)."
    )
    onnx: bool = Field(True, description="Also export the classifier as ONNX.")
    report: bool = Field(True, description="Also write the calibration report.")


class BIDSExportConfig(ApiRequest):
    """Export a subject's sessions as a BIDS dataset (a zip artifact of kind ``bids``)."""

    subject_id: int = Field(ge=1, le=MAX_ROW_ID)


class SessionReplayConfig(ApiRequest):
    """Replay an online session through the live decoder and the learner (a new pi_HF)."""

    session_id: int = Field(ge=1, le=MAX_ROW_ID)
    classifier_id: int | None = Field(
        None,
        ge=1,
        le=MAX_ROW_ID,
        description="Decode with this classifier (default: the session's).",
    )
    label_budget: int | None = Field(
        None, ge=1, le=100_000, description="Labels of the new pi_HF (default: the session's)."
    )


CONFIG_MODELS: dict[str, type[ApiRequest]] = {
    "guided_ppo": GuidedPPOConfig,
    "reproduce": ReproduceConfig,
    "eeg_calibration": EEGCalibrationConfig,
    "bids_export": BIDSExportConfig,
    "session_replay": SessionReplayConfig,
}


class JobCreate(ApiRequest):
    """A job to run: its kind and that kind's config."""

    kind: JobKind
    config: dict[str, Any] = Field(default_factory=dict)


class JobPublic(PublicModel):
    """A job: status, progress and where its results are (the curve has its own route)."""

    id: str
    kind: str
    config: dict[str, Any]
    status: JobStatus
    progress: float
    attempts: int
    max_attempts: int
    resumed_from_step: int | None
    steps_done: int
    error: str | None
    result: dict[str, Any] | None
    submitter_id: int | None
    parent_id: str | None
    cancel_requested: bool
    checkpoint_artifact_id: str | None
    model_artifact_id: str | None
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class CurvePublic(PublicModel):
    """The job's learning curve: ``[step, SPL]`` pairs of the greedy evaluations so far."""

    job_id: str
    curve: list[tuple[int, float]]


class JobLogEntry(BaseModel):
    """One event of a job: who submitted, cancelled or retried it, when it started, resumed,
    and how it ended."""

    at: datetime
    event: str = Field(description="submitted, cancel requested, retried, started, finished...")
    detail: str = ""
    actor_email: str | None = None


class JobLogPublic(BaseModel):
    """A job's events, oldest first."""

    job_id: str
    items: list[JobLogEntry]
