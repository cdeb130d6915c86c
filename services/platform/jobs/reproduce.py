"""``reproduce``: a reproduction of Fig. 3 fanned out over the workers: ``reproduce_batch``
jobs of up to ``batch_runs`` runs in lockstep each, or with ``batch_runs`` 1 one
``reproduce_run`` job per run."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import Field, field_validator, model_validator

from services.platform.jobs.kind import JobConfig, JobKind
from services.platform.jobs.ppo import (
    Method,
    PPOOverrides,
    Preset,
    Task,
    Treatment,
    bounded,
    lower_task,
)

MAX_REPRODUCE_RUNS = 2000
MAX_BATCH_RUNS = 32
"""Most runs of one ``reproduce_batch`` job: the learner's ``pool.LOCKSTEP_MAX_RUNS``."""


class ReproduceConfig(JobConfig):
    """A reproduction of Fig. 3 (``bgrl reproduce`` options): the runs in lockstep batches of
    at most ``batch_runs``, one batch per worker task (``batch_runs`` 1: one run each).

    Not offered: ``--out`` (the results are the job's artifacts), ``--workers`` (the runs
    are spread over the Celery workers) and ``--map`` (a path on the api's host; workers run
    every job on the sim's default map).
    """

    quick: bool = Field(False, title="Quick", description="2 seeds (unless seeds is given).")
    seeds: int | None = Field(
        None,
        ge=1,
        le=100,
        title="Seeds per configuration",
        description="Default 10 (2 if quick).",
    )
    first_seed: int = bounded("seed", 0, title="First seed")
    # plain defaults (pydantic copies them per config) so that the JSON Schema shows them
    tasks: list[Task] = Field(["sssg", "vssg"], min_length=1, title="Tasks")
    methods: list[Method] = Field(
        ["rl_sparse", "rl_rich", "hf_sparse"], min_length=1, title="Methods"
    )
    accuracies: list[float] = Field(
        [0.55, 0.6, 0.7],
        min_length=1,
        title="Accuracies C",
        description="Simulated feedback accuracies of the hf_sparse runs, each 0 to 1.",
        json_schema_extra={"items": {"type": "number", "minimum": 0, "maximum": 1}},
    )
    treatments: list[Treatment] = Field(
        ["authors"],
        min_length=1,
        title="HF treatments",
        description="How PPO treats pi_HF's actions in the hf_sparse runs.",
    )
    ppo: PPOOverrides = Field(default_factory=PPOOverrides, title="PPO settings")
    preset: Preset = Field(
        "paper",
        title="Preset",
        description="paper: the paper's settings; platform: the recommended ones (treatments "
        "['authors'] become ['truncated_is'], ppo.hf_guide_sampling true and ppo.sil_coef 1 "
        "(self-imitation, every method alike) unless given, pi_HF learned with the "
        "recommended stage-2 method).",
    )
    checkpoint_every: int | None = Field(
        None,
        ge=1,
        le=100_000,
        title="Checkpoint every",
        description="PPO updates between checkpoints of each run.",
    )
    n_labels: int = Field(
        1000, ge=1, le=1_000_000, title="Feedback labels",
        description="Labels each hf_sparse run learns pi_HF from (every labelled action).",
    )  # fmt: skip
    batch_runs: int = Field(
        8,
        ge=1,
        le=MAX_BATCH_RUNS,
        title="Runs per batch",
        description="Runs of one PPO shape trained together in lockstep by one worker (the "
        "same records as alone); 1: each run alone (bgrl reproduce --single-run).",
    )

    @field_validator("tasks", mode="before")
    @classmethod
    def _lower_tasks(cls, value: object) -> object:
        return [lower_task(v) for v in value] if isinstance(value, list) else value

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


def summary(config: Mapping[str, Any]) -> str:
    """``SSSG+VSSG rl_sparse, hf_sparse; 10 seed(s)``."""
    tasks = "+".join(str(t).upper() for t in config.get("tasks") or [])
    methods = ", ".join(str(m) for m in config.get("methods") or [])
    return f"{tasks} {methods}; {config.get('seeds', '?')} seed(s)"


KIND = JobKind(
    name="reproduce",
    title="Reproduction sweep (Fig. 3)",
    config=ReproduceConfig,
    summary=summary,
    counts_steps=True,
)
