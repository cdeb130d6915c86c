"""Checkpoints of a PPO run: weights, optimiser, generators and run state, written atomically.

A checkpoint is written at an update boundary; :func:`services.learner.ppo.train` resumes
from it by restoring everything here, re-seeding the env with the current episode's reset
seed and replaying that episode's actions (the env is deterministic), so a resumed run ends
exactly as an uninterrupted one.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from services.core.files import write_bytes_atomic
from services.learner.feedback import HFPolicy
from services.learner.optimizer import FlatAdam
from services.learner.seeding import TrainingResets

CHECKPOINT_VERSION = 3
"""2: the training reset seeds are a stream of their own (``resets``); 3: the best
evaluation's step, SPL and weights (``best_agent``)."""


@dataclass
class RunState:
    """Everything that changes during training besides weights, optimiser and generators."""

    global_step: int = 0
    n_updates: int = 0
    n_episodes: int = 0
    n_hf_episodes: int = 0
    episode_seed: int = 0
    """Reset seed of the episode in progress."""
    episode_actions: list[int] = field(default_factory=list)
    """Actions taken so far in the episode in progress (replayed on resume)."""
    episode_is_hf: bool = False
    episode_handed_over: bool = False
    """The pi_HF episode in progress revisited an observation and follows pi_RL since
    (``hf_handover_on_revisit``)."""
    episode_seen: set[bytes] = field(default_factory=set)
    """Observations where the pi_HF episode in progress chose an action
    (``hf_handover_on_revisit``)."""
    episode_return: float = 0.0
    visits: dict[tuple[int, int, int], int] = field(default_factory=dict)
    """Visits per pose cell so far (``explore_coef``)."""
    episodes: list[tuple[int, int, bool, bool, bool]] = field(default_factory=list)
    """Per finished episode: (env step at its end, length, success, collision, followed pi_HF)."""
    curve: list[tuple[int, float]] = field(default_factory=list)
    metrics: list[dict[str, float]] = field(default_factory=list)
    best_step: int | None = None
    """Env step of the best evaluation so far (the first of equal bests)."""
    best_spl: float | None = None
    """SPL of that evaluation."""


@dataclass
class Checkpoint:
    """What a checkpoint file holds."""

    config: dict[str, Any]
    """``asdict(PPOConfig)``: a checkpoint only resumes the run it was written by."""
    agent: dict[str, torch.Tensor]
    optimizer: dict[str, Any]
    rng: dict[str, Any]
    """State of the actions generator."""
    resets: dict[str, Any]
    """State of the training-reset generator."""
    state: RunState
    hf_model: dict[str, torch.Tensor] | None
    """Fhat's weights (pi_HF), when the run is guided."""
    best_agent: dict[str, torch.Tensor] | None = None
    """pi_RL's weights at the best evaluation so far (``state.best_step``)."""
    success_replay: dict[str, torch.Tensor] | None = None
    """The self-imitation buffer (``SuccessReplay.state_dict``), when ``sil_coef > 0``."""

    @classmethod
    def capture(
        cls,
        config: dict[str, Any],
        agent: nn.Module,
        optimizer: FlatAdam,
        rng: np.random.Generator,
        resets: TrainingResets,
        state: RunState,
        hf_policy: HFPolicy | None,
        *,
        best_agent: dict[str, torch.Tensor] | None = None,
        success_replay: dict[str, torch.Tensor] | None = None,
    ) -> Checkpoint:
        """Everything a run needs to continue exactly (``config`` is ``asdict(PPOConfig)``)."""
        return cls(
            config=config,
            agent=agent.state_dict(),
            optimizer=optimizer.state_dict(),
            rng=rng.bit_generator.state,
            resets=resets.state,
            state=state,
            hf_model=None if hf_policy is None else hf_policy.model.state_dict(),
            best_agent=best_agent,
            success_replay=success_replay,
        )

    def restore(
        self,
        agent: nn.Module,
        optimizer: FlatAdam,
        rng: np.random.Generator,
        resets: TrainingResets,
        hf_policy: HFPolicy | None,
    ) -> RunState:
        """Load weights, optimiser and generator states in place; return the run state."""
        agent.load_state_dict(self.agent)
        optimizer.load_state_dict(self.optimizer)
        rng.bit_generator.state = self.rng
        resets.state = self.resets
        if hf_policy is not None and self.hf_model is not None:
            hf_policy.model.load_state_dict(self.hf_model)
        return self.state


def save_checkpoint(path: Path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` atomically (never a half-written file)."""
    payload = {"version": CHECKPOINT_VERSION, **asdict(checkpoint)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_bytes_atomic(path, buffer.getvalue())


def load_checkpoint(
    path: Path, config: dict[str, Any], defaults: dict[str, Any] | None = None
) -> Checkpoint:
    """Read a checkpoint written for ``config`` (``asdict(PPOConfig)``); ValueError if not.

    A setting missing from the checkpoint's config (written before the setting existed) is
    taken at its value in ``defaults`` (``asdict(PPOConfig())``: what that code did), so a
    run checkpointed before an upgrade resumes after it as long as it keeps those values.
    """
    try:  # weights_only: tensors and plain containers, never code from the file
        payload = torch.load(path, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as exc:
        raise ValueError(
            f"{path}: not a readable checkpoint (truncated or corrupt? delete it to start the "
            f"run afresh): {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
        ) from exc
    if not isinstance(payload, dict) or payload.get("version") != CHECKPOINT_VERSION:
        version = payload.get("version") if isinstance(payload, dict) else None
        raise ValueError(f"{path}: unsupported checkpoint version {version}")
    written_with = {**(defaults or {}), **payload["config"]}
    if written_with != config:
        changed = sorted(
            key for key in {*config, *written_with} if written_with.get(key) != config.get(key)
        )
        raise ValueError(
            f"{path}: checkpoint was written with a different PPOConfig ({', '.join(changed)})"
        )
    state = RunState(**payload["state"])
    state.curve = [(int(step), float(spl)) for step, spl in state.curve]
    state.episodes = [tuple(e) for e in state.episodes]  # type: ignore[misc]
    del payload["version"]
    return Checkpoint(**{**payload, "state": state})
