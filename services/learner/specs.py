"""What one run of the simulated-feedback experiment (paper Fig. 3) is: :class:`RunSpec`.

A spec is a frozen, JSON-able description: a process pool or a Celery worker takes one and
returns a :class:`~services.learner.runs.RunRecord`. ``RunSpec.to_dict()`` has the field
names of the ``spec`` of every run in ``results.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from services.core.feedback import LABEL_CHANNELS
from services.learner.evaluation import eval_seeds
from services.learner.hf_methods import PAPER_METHOD, RECOMMENDED_METHOD, get_method
from services.learner.ppo import PPOConfig

TASK_ENV_IDS = {"sssg": "services.sim:BrainNav-SSSG-v0", "vssg": "services.sim:BrainNav-VSSG-v0"}
METHODS = ("rl_sparse", "rl_rich", "rl_shaped", "hf_sparse")
PAPER_METHODS = ("rl_sparse", "rl_rich", "hf_sparse")
"""The paper's three methods (Fig. 3); rl_shaped is ours, a hand-designed-reward baseline."""
REWARD_MODES = {
    "rl_sparse": "sparse",
    "rl_rich": "dense",
    "rl_shaped": "shaped",
    "hf_sparse": "sparse",
}
"""The env's reward of each method. rl_rich learns from the dense reward (geodesic distance
cost, crash charged its cost for ever: docs/sim.md), not from the paper's rich reward as
specified (``rich``, a crash trap); rl_shaped: sparse + potential-based shaping."""
ACCURACIES = (0.55, 0.6, 0.7)
TREATMENTS = ("authors", "truncated_is")
N_VSSG_EVAL_STARTS = 5
QUICK_SEEDS = 2
FULL_SEEDS = 10
DEFAULT_LABELS = 1000
"""Labels pi_HF is learned from (every labelled action), the paper's budget."""
FEEDBACKS = ("oracle", "virtual_subject")
"""Where an hf_sparse run's labels come from: the noisy oracle at accuracy C (the paper's
simulated feedback) or the virtual subject decoded by its own calibrated decoder
(end to end, ``services.worker.e2e_feedback``)."""
DECODER_ACCURACY_TOLERANCE = 0.02
"""How close a virtual subject's decoder's held-out accuracy must come to its target (the
subject finder's tolerance). A run whose subject got no closer is kept and reported, with
its measured ``decoder_accuracy`` (docs/protocol.md, "Before the runs")."""
PRESETS = ("paper", "platform")
"""Settings of a reproduction (``bgrl reproduce --preset``, ``reproduce`` jobs): the paper's
or the platform's recommended ones."""
RUN_FIXED_PPO_FIELDS = frozenset({"env_id", "env_kwargs", "seed", "eval_seeds", "hf_treatment"})
"""PPOConfig fields a spec sets per run; ``ppo_overrides`` may not change them."""


@dataclass(frozen=True)
class RunSpec:
    """One run: a task, a method, a seed, and what is held fixed (map, labels, PPO).

    ``accuracy`` (the simulated feedback's C) is required for ``hf_sparse`` with the
    ``oracle``'s feedback and None otherwise; ``decoder_accuracy`` (the target held-out
    accuracy of the virtual subject's decoder) is required for ``virtual_subject`` feedback
    and None otherwise; ``hf_treatment`` is ``authors`` or ``truncated_is`` for ``hf_sparse``
    (default ``authors``) and None otherwise.
    """

    task: str
    method: str
    seed: int
    accuracy: float | None = None
    hf_treatment: str | None = None
    n_labels: int = DEFAULT_LABELS
    map_path: str | None = None
    ppo_overrides: Mapping[str, Any] = field(default_factory=dict)
    hf_method: str | None = None
    """Stage-2 method that learns pi_HF (:mod:`services.learner.hf_methods`): ``paper`` by
    default for hf_sparse, None otherwise."""
    feedback: str = "oracle"
    """Where the labels come from (:data:`FEEDBACKS`)."""
    label_channel: str = "hard"
    """How stage 2 reads a label: ``hard`` or ``soft`` (virtual_subject feedback only)."""
    decoder_accuracy: float | None = None
    """virtual_subject feedback: the target held-out accuracy of the subject's decoder."""

    def __post_init__(self) -> None:
        if self.task not in TASK_ENV_IDS:
            raise ValueError(f"unknown task {self.task!r}; expected one of {sorted(TASK_ENV_IDS)}")
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {METHODS}")
        check_feedback(self.method == "hf_sparse", self.feedback, self.label_channel)
        oracle = self.method == "hf_sparse" and self.feedback == "oracle"
        if oracle != (self.accuracy is not None):
            raise ValueError(
                "accuracy is required for hf_sparse with the oracle's feedback and must be "
                "None otherwise"
            )
        if self.accuracy is not None and not 0.0 <= self.accuracy <= 1.0:
            raise ValueError(f"accuracy must be in [0, 1], got {self.accuracy}")
        check_decoder_accuracy(self.feedback, self.decoder_accuracy)
        treatment = self.hf_treatment
        if self.method == "hf_sparse":
            treatment = treatment or "authors"
            if treatment not in TREATMENTS:
                raise ValueError(
                    f"unknown hf_treatment {treatment!r}; expected one of {TREATMENTS}"
                )
        elif treatment not in (None, "authors"):
            raise ValueError(f"hf_treatment applies to hf_sparse only, not {self.method}")
        else:
            treatment = None
        if self.seed < 0 or self.n_labels < 1:
            raise ValueError("seed must be >= 0 and n_labels >= 1")
        hf_method = self.hf_method
        if self.method == "hf_sparse":
            hf_method = get_method(hf_method or PAPER_METHOD).name
        elif hf_method not in (None, PAPER_METHOD):
            raise ValueError(f"hf_method applies to hf_sparse only, not {self.method}")
        else:
            hf_method = None
        object.__setattr__(self, "hf_method", hf_method)
        fixed = RUN_FIXED_PPO_FIELDS & set(self.ppo_overrides)
        if fixed:
            raise ValueError(f"ppo_overrides cannot set {sorted(fixed)}: the spec sets them")
        object.__setattr__(self, "hf_treatment", treatment)
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "n_labels", int(self.n_labels))
        object.__setattr__(self, "ppo_overrides", dict(self.ppo_overrides))
        try:
            self.ppo_config()  # unknown or inconsistent PPO settings fail here, not in a worker
        except TypeError as exc:
            raise ValueError(f"ppo_overrides: {exc}") from None

    @property
    def key(self) -> tuple[Any, ...]:
        """Identity of the run inside a reproduction (what resuming matches on); a stage-2
        method other than the paper's is appended, so earlier keys stay as they were."""
        key = (self.task, self.method, self.accuracy, self.seed, self.hf_treatment)
        key = key if self.hf_method in (None, PAPER_METHOD) else (*key, self.hf_method)
        if self.feedback == "oracle":
            return key
        return (*key, self.feedback, self.label_channel, self.decoder_accuracy)

    @property
    def label(self) -> str:
        """Short human-readable name, e.g. ``vssg hf_sparse C=0.7 [authors] seed=3``."""
        parts = [self.task, self.method]
        if self.method == "hf_sparse":
            if self.accuracy is not None:
                parts.append(f"C={self.accuracy:g}")
            else:
                parts.append(f"subject@{self.decoder_accuracy:g} {self.label_channel}")
            parts.append(f"[{self.hf_treatment}]")
            if self.hf_method != PAPER_METHOD:
                parts.append(str(self.hf_method))
        return " ".join([*parts, f"seed={self.seed}"])

    def ppo_config(self) -> PPOConfig:
        """The run's PPOConfig: the same network and hyperparameters for every method."""
        env_kwargs: dict[str, Any] = {"reward_mode": REWARD_MODES[self.method]}
        if self.map_path is not None:
            env_kwargs["map_path"] = self.map_path
        config = PPOConfig(
            env_id=TASK_ENV_IDS[self.task],
            env_kwargs=env_kwargs,
            seed=self.seed,
            eval_seeds=eval_seeds(self.task, N_VSSG_EVAL_STARTS),
            hf_treatment=self.hf_treatment or "authors",  # type: ignore[arg-type]
            **self.ppo_overrides,
        )
        if self.method in ("rl_rich", "rl_shaped"):  # their rewards use the learner's discount
            config.env_kwargs["shaping_gamma"] = config.gamma
        return config

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (the ``spec`` of a run in ``results.json``)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunSpec:
        """Rebuild from :meth:`to_dict` output (or a ``results.json`` spec)."""
        return cls(**data)


def check_feedback(uses_feedback: bool, feedback: str, label_channel: str) -> None:
    """``ValueError`` for an unknown feedback or channel, feedback other than the oracle's
    where no labels are used, or the soft channel without a decoder behind it."""
    if feedback not in FEEDBACKS:
        raise ValueError(f"unknown feedback {feedback!r}; expected one of {FEEDBACKS}")
    if label_channel not in LABEL_CHANNELS:
        raise ValueError(
            f"unknown label_channel {label_channel!r}; expected one of {LABEL_CHANNELS}"
        )
    if not uses_feedback and (feedback, label_channel) != ("oracle", "hard"):
        raise ValueError("feedback and label_channel apply to hf_sparse only")
    if label_channel == "soft" and feedback != "virtual_subject":
        raise ValueError(
            "the soft label channel needs a decoder's likelihood ratios: use "
            "feedback virtual_subject (the noisy oracle gives hard labels only)"
        )


def check_decoder_accuracy(feedback: str, decoder_accuracy: float | None) -> None:
    """``ValueError`` unless ``decoder_accuracy`` is given (in (0.5, 1)) exactly for the
    virtual subject's feedback."""
    if (feedback == "virtual_subject") != (decoder_accuracy is not None):
        raise ValueError(
            "decoder_accuracy is required for virtual_subject feedback and must be None otherwise"
        )
    if decoder_accuracy is not None and not 0.5 < decoder_accuracy < 1.0:
        raise ValueError(f"decoder_accuracy must be in (0.5, 1), got {decoder_accuracy}")


def with_feedback(specs: Sequence[RunSpec], feedback: str, label_channel: str) -> list[RunSpec]:
    """The specs with their hf_sparse runs' labels from ``feedback`` through
    ``label_channel``; for ``virtual_subject`` an hf_sparse spec's accuracy becomes the
    target decoder accuracy (``--accuracies`` lists C for the oracle, the decoder's
    accuracy for the virtual subject)."""
    if feedback == "oracle" and label_channel == "hard":
        return list(specs)
    out = []
    for spec in specs:
        if spec.method != "hf_sparse":
            out.append(spec)
            continue
        virtual = feedback == "virtual_subject"
        out.append(
            replace(
                spec,
                feedback=feedback,
                label_channel=label_channel,
                accuracy=None if virtual else spec.accuracy,
                decoder_accuracy=spec.accuracy if virtual else None,
            )
        )
    return out


def settings_conflict(specs: Sequence[RunSpec]) -> bool:
    """True if the specs differ in map, PPO overrides or (for hf_sparse) label count or
    stage-2 method (a folder's summary and CSV do not tell two apart)."""
    base = {json.dumps([s.map_path, s.ppo_overrides], sort_keys=True) for s in specs}
    stage2 = {(s.n_labels, s.hf_method) for s in specs if s.method == "hf_sparse"}
    return len(base) > 1 or len(stage2) > 1


def build_specs(
    *,
    seeds: int,
    tasks: Sequence[str] = ("sssg", "vssg"),
    methods: Sequence[str] = PAPER_METHODS,
    accuracies: Sequence[float] = ACCURACIES,
    treatments: Sequence[str] = ("authors",),
    first_seed: int = 0,
    map_path: str | None = None,
    ppo_overrides: Mapping[str, Any] | None = None,
    hf_method: str | None = None,
    n_labels: int = DEFAULT_LABELS,
) -> list[RunSpec]:
    """Every run of a reproduction, seed-major so early results cover every method; every
    hf_sparse run learns pi_HF from ``n_labels`` labels."""
    overrides = dict(ppo_overrides or {})
    specs = []
    for seed in range(first_seed, first_seed + seeds):
        for task in tasks:
            for method in methods:
                if method != "hf_sparse":
                    specs.append(
                        RunSpec(task, method, seed, None, None, DEFAULT_LABELS, map_path, overrides)
                    )
                    continue
                for treatment in treatments:
                    for accuracy in accuracies:
                        specs.append(
                            RunSpec(
                                task,
                                method,
                                seed,
                                accuracy,
                                treatment,
                                n_labels,
                                map_path,
                                overrides,
                                hf_method,
                            )
                        )
    return specs


PLATFORM_SIL_COEF = 1.0
"""Self-imitation in the platform preset (docs/reproduction.md, "Self-imitation")."""


def apply_preset(
    preset: str, treatments: Sequence[str], ppo_overrides: Mapping[str, Any]
) -> tuple[list[str], dict[str, Any], str]:
    """(treatments, PPO overrides, stage-2 method) of a reproduction with ``preset``.

    ``paper`` changes nothing (the paper's Fhat); ``platform`` replaces the default
    treatment (authors) by truncated_is, adds ``hf_guide_sampling=True`` and self-imitation
    (``sil_coef=1.0``, for every method of the reproduction alike) unless the overrides set
    them, and selects the recommended stage-2 method (docs/stage2.md).
    """
    if preset not in PRESETS:
        raise ValueError(f"preset: unknown preset {preset!r}; expected one of {PRESETS}")
    treatments, overrides = list(treatments), dict(ppo_overrides)
    if preset == "paper":
        return treatments, overrides, PAPER_METHOD
    overrides.setdefault("hf_guide_sampling", True)
    overrides.setdefault("sil_coef", PLATFORM_SIL_COEF)
    return (
        (["truncated_is"] if treatments == ["authors"] else treatments),
        overrides,
        (RECOMMENDED_METHOD),
    )
