"""What the training kinds' configs take from the learner, which the platform cannot import
(the api stays free of torch): tasks, methods, treatments, presets, and the PPO settings a
job may override with the learner's own bounds (:data:`services.core.ppo_bounds
.SETTING_BOUNDS`, the table ``PPOConfig`` enforces). Tests hold each list equal to the
learner's.

The platform adds one thing: :data:`JOB_CAPS`, the largest value a queued job may ask for
(what a job may cost a shared worker); a setting's lower bound is always the learner's.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import Field

from services.core.ppo_bounds import SETTING_BOUNDS
from services.platform.jobs.kind import JobConfig

Task = Literal["sssg", "vssg"]
Method = Literal["rl_sparse", "rl_rich", "rl_shaped", "hf_sparse"]
Treatment = Literal["authors", "truncated_is"]
Preset = Literal["paper", "platform"]
"""Settings of a reproduction (``bgrl reproduce --preset``); the learner's ``PRESETS``."""
PRESETS: tuple[str, ...] = Preset.__args__  # type: ignore[attr-defined]

MAX_TOTAL_STEPS = 2_000_000
MAX_SEED = 2**31 - 1
PPO_DEFAULT_N_STEPS = 128
PPO_DEFAULT_MINIBATCH_SIZE = 64

JOB_CAPS: dict[str, float] = {
    "seed": MAX_SEED,
    "total_steps": MAX_TOTAL_STEPS,
    "n_steps": 100_000,
    "n_epochs": 1000,
    "minibatch_size": 100_000,
    "learning_rate": 1,
    "adam_eps": 1,
    "clip_coef": 10,
    "ent_coef": 10,
    "vf_coef": 100,
    "max_grad_norm": 1e6,
    "target_kl": 10,
    "reward_scale": 1e6,
    "hidden_sizes": 4096,
    "eval_every": MAX_TOTAL_STEPS,
    "hf_warmup_steps": MAX_TOTAL_STEPS,
    "is_clip": 100,
    "hf_prior_coef": 100,
    "hf_withdraw_after": MAX_TOTAL_STEPS,
    "explore_coef": 1e6,
    "explore_cell_m": 100,
    "sil_coef": 100,
    "sil_updates": 10_000,
    "sil_value_coef": 100,
    "sil_capacity": 10_000_000,
}
"""Largest value of a PPO setting a job may ask for (of each layer for ``hidden_sizes``);
settings the learner bounds above (gamma, ...) keep the learner's upper bound."""


def bounded(name: str, default: Any = None, **extra: Any) -> Any:
    """A pydantic ``Field`` of PPO setting ``name`` with the learner's bounds, capped by
    :data:`JOB_CAPS`."""
    low, high, low_open = SETTING_BOUNDS[name]
    high = min(high, JOB_CAPS.get(name, math.inf))
    limits: dict[str, float] = {"gt" if low_open else "ge": low}
    if math.isfinite(high):
        limits["le"] = high
    return Field(default, **limits, **extra)


class PPOOverrides(JobConfig):
    """PPO settings to change (``bgrl reproduce --ppo KEY=VALUE``); omitted ones keep defaults.

    ``env_id``, ``env_kwargs``, ``seed``, ``eval_seeds`` and ``hf_treatment`` are set per run
    and cannot be overridden.
    """

    total_steps: int | None = bounded("total_steps")
    n_steps: int | None = bounded("n_steps")
    n_epochs: int | None = bounded("n_epochs")
    minibatch_size: int | None = bounded("minibatch_size")
    learning_rate: float | None = bounded("learning_rate")
    anneal_lr: bool | None = None
    adam_eps: float | None = bounded("adam_eps")
    gamma: float | None = bounded("gamma")
    gae_lambda: float | None = bounded("gae_lambda")
    clip_coef: float | None = bounded("clip_coef")
    ent_coef: float | None = bounded("ent_coef")
    vf_coef: float | None = bounded("vf_coef")
    max_grad_norm: float | None = bounded("max_grad_norm")
    target_kl: float | None = bounded("target_kl")
    norm_adv: bool | None = None
    reward_scale: float | None = bounded("reward_scale")
    hidden_sizes: list[Annotated[int, bounded("hidden_sizes", ...)]] | None = Field(
        None, min_length=1, max_length=8, description="Units of each hidden layer."
    )
    eval_every: int | None = bounded("eval_every")
    hf_eps_init: float | None = bounded("hf_eps_init")
    hf_t_trans_fraction: float | None = bounded("hf_t_trans_fraction")
    hf_warmup_steps: int | None = bounded("hf_warmup_steps")
    is_clip: float | None = bounded("is_clip")
    hf_guide_sampling: bool | None = None
    hf_prior_coef: float | None = bounded("hf_prior_coef")
    hf_handover_on_revisit: bool | None = None
    hf_hold_until_success: bool | None = None
    hf_withdraw_after: int | None = bounded("hf_withdraw_after")
    explore_coef: float | None = bounded("explore_coef")
    explore_cell_m: float | None = bounded("explore_cell_m")
    sil_coef: float | None = bounded("sil_coef")
    sil_updates: int | None = bounded("sil_updates")
    sil_value_coef: float | None = bounded("sil_value_coef")
    sil_capacity: int | None = bounded("sil_capacity")

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


def lower_task(value: object) -> object:
    """Tasks are case-insensitive (``SSSG`` is ``sssg``)."""
    return value.lower() if isinstance(value, str) else value
