"""``guided_ppo``: one training run of (guided) PPO, submitted on its own."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import Field, ValidationInfo, field_validator, model_validator

from services.core.hf_methods import HFMethodName
from services.core.schemas import MAX_ROW_ID
from services.platform.jobs.kind import JobConfig, JobKind, form_hints
from services.platform.jobs.ppo import (
    Method,
    PPOOverrides,
    Preset,
    Task,
    Treatment,
    bounded,
    lower_task,
)

HF_ONLY = form_hints(shown_when={"method": ["hf_sparse"]})
"""Settings of HF-guided runs only (the form shows them for ``hf_sparse``)."""


class GuidedPPOConfig(JobConfig):
    """One training run of (guided) PPO: ``bgrl`` learner's run of one task, method and seed."""

    task: Task = Field(title="Task", description="SSSG or VSSG (case-insensitive).")
    method: Method = Field(
        title="Method",
        description="rl_sparse, rl_rich, rl_shaped: PPO alone; hf_sparse: guided by pi_HF.",
    )
    accuracy: float | None = Field(
        None,
        ge=0,
        le=1,
        title="Feedback accuracy C",
        description="Accuracy of the simulated feedback pi_HF learns from (0 to 1; e.g. 0.7), "
        "unless a stored pi_HF is given.",
        json_schema_extra=HF_ONLY,
    )
    seed: int = bounded("seed", 0, title="Seed")
    total_steps: int = bounded("total_steps", 40_000, title="Total steps")
    hf_treatment: Treatment = Field(
        "authors",
        title="HF treatment",
        description="How PPO treats pi_HF's actions: the authors' way or truncated "
        "importance sampling.",
        json_schema_extra=HF_ONLY,
    )
    ppo: PPOOverrides = Field(default_factory=PPOOverrides, title="PPO settings")
    preset: Preset = Field(
        "paper",
        title="Preset",
        description="PPO settings: paper (the paper's) or platform (the recommended ones: "
        "hf_treatment 'authors' becomes 'truncated_is', ppo.hf_guide_sampling true and "
        "ppo.sil_coef 1 unless given). The stage-2 method is hf_method's either way.",
    )
    hf_model_id: int | None = Field(
        None,
        ge=1,
        le=MAX_ROW_ID,
        title="Human-feedback policy",
        description="A stored pi_HF to guide with (hf_sparse) instead of training one.",
        json_schema_extra=form_hints(shown_when={"method": ["hf_sparse"]}, references="hf-models"),
    )
    n_labels: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        title="Feedback labels",
        description="Feedback labels pi_HF is trained on (hf_sparse).",
        json_schema_extra=HF_ONLY,
    )
    hf_method: HFMethodName | None = Field(
        None,
        title="Stage-2 method",
        description="Stage-2 method that learns pi_HF (hf_sparse; docs/stage2.md); default "
        "the platform's recommended one, 'paper' the paper's Fhat. Not with a stored pi_HF.",
        json_schema_extra=form_hints(shown_when={"method": ["hf_sparse"], "hf_model_id": [None]}),
    )
    checkpoint_every: int | None = Field(
        None,
        ge=1,
        le=100_000,
        title="Checkpoint every",
        description="PPO updates between checkpoints (worker default).",
    )

    _lower_task = field_validator("task", mode="before")(lower_task)

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


def run_summary(config: Mapping[str, Any]) -> str:
    """``SSSG hf_sparse C=0.7 seed 3, 40,000 steps`` (a guided_ppo config or a run spec)."""
    accuracy = config.get("accuracy")
    text = f"{str(config.get('task', '')).upper()} {config.get('method', '')}"
    text += f" C={accuracy}" if accuracy is not None else ""
    text += f" seed {config.get('seed', 0)}"
    steps = config.get("total_steps") or (config.get("ppo_overrides") or {}).get("total_steps")
    return f"{text}, {int(steps):,} steps" if steps else text


KIND = JobKind(
    name="guided_ppo",
    title="Guided-PPO run",
    config=GuidedPPOConfig,
    summary=run_summary,
    counts_steps=True,
)
