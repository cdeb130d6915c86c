"""What :func:`services.learner.ppo.train` (and ``train_lockstep``) take and give besides
their config.

:class:`Callback` (progress hooks that can stop training, SB3 style), :class:`TrainResult`
and the TorchScript export of a trained policy (:class:`PolicyExport`).
"""

from __future__ import annotations

import copy
import json
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from services.learner.networks import exported_observations
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig

Checkpointed = Literal["last", "best"]
"""Which weights of a run: the ``last`` (end of training) or the ``best`` evaluation's."""


class PolicyExport(nn.Module):
    """What TorchScript export contains: normalisation + actor. ``forward`` gives logits."""

    def __init__(self, agent: ActorCritic) -> None:  # any module giving (logits, value)
        super().__init__()
        self.agent = agent
        self.n_obs: int = int(agent.normalizer.n_obs)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Action logits for raw (unnormalised) observations of shape (n_obs,) or a batch
        (..., n_obs), of any real dtype (float64 too)."""
        obs = exported_observations(obs, self.n_obs)
        logits, _ = self.agent(obs.reshape(-1, self.n_obs))
        return logits.reshape(obs.shape[:-1] + [logits.shape[-1]])  # noqa: RUF005 (TorchScript)

    @torch.jit.export
    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """Greedy action(s)."""
        return torch.argmax(self.forward(obs), dim=-1)


class Callback:
    """Progress hooks; each returns False to stop training (SB3 style)."""

    def on_step(self, global_step: int, info: dict[str, Any]) -> bool:
        """After every env step."""
        return True

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        """After every PPO update (metrics named like CleanRL's)."""
        return True

    def on_eval(self, global_step: int, spl: float) -> bool:
        """After every SPL evaluation."""
        return True


@dataclass
class TrainResult:
    """Outcome of :func:`train`."""

    config: PPOConfig
    agent: ActorCritic
    curve: list[tuple[int, float]]
    """``(env_steps, SPL of the greedy pi_RL)`` at every evaluation."""
    metrics: list[dict[str, float]]
    """One CleanRL-named metrics dict per update."""
    global_step: int
    n_episodes: int
    n_hf_episodes: int
    episodes: list[tuple[int, int, bool, bool, bool]]
    """Per finished training episode: (env step at its end, length, success, collision,
    followed pi_HF)."""
    stopped_early: bool
    wall_seconds: float
    best_step: int | None = None
    """Env step of the best evaluation (the first of equal bests)."""
    best_agent: dict[str, torch.Tensor] | None = None
    """pi_RL's weights at ``best_step`` (the last weights are ``agent``'s)."""

    @property
    def final_spl(self) -> float:
        """SPL at the last evaluation."""
        return self.curve[-1][1]

    @property
    def best_spl(self) -> float:
        """SPL at the best evaluation."""
        return max(spl for _, spl in self.curve)

    def best_policy(self) -> ActorCritic:
        """A copy of the agent with the best evaluation's weights (``agent`` is the last)."""
        best = copy.deepcopy(self.agent)
        if self.best_agent is not None:
            best.load_state_dict(self.best_agent)
        return best

    def act(self, obs: np.ndarray) -> int:
        """Greedy action of the trained policy for one observation (shape ``(n_obs,)``; a
        batch is refused: the exported module's ``act`` takes one)."""
        obs = np.asarray(obs, dtype=np.float32)
        n_obs = self.agent.normalizer.n_obs
        if obs.shape != (n_obs,):
            raise ValueError(
                f"act takes one observation of shape ({n_obs},), got shape {obs.shape}; "
                "for a batch use export_torchscript(...) and the module's act"
            )
        with torch.no_grad():
            logits, _ = self.agent(torch.as_tensor(obs))
        return int(torch.argmax(logits))

    def export_torchscript(self, path: str | Path, *, which: Checkpointed = "last") -> Path:
        """Save normalisation + actor as TorchScript (``torch.jit.load`` needs no project).

        ``which``: the ``last`` weights or the ``best`` evaluation's; the file's
        ``bgrl_meta.json`` says which, at what step and SPL.
        """
        if which not in ("last", "best"):
            raise ValueError(f"which must be 'last' or 'best', not {which!r}")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        agent = self.agent if which == "last" else self.best_policy()
        with warnings.catch_warnings():  # TorchScript is deprecated but still the format
            warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.load reads anywhere
            scripted = torch.jit.script(PolicyExport(agent).eval())
        step, spl = (
            (self.global_step, self.final_spl)
            if which == "last"
            else (self.best_step, self.best_spl)
        )
        meta = {
            "config": asdict(self.config),
            "final_spl": self.final_spl,
            "checkpoint": which,
            "step": step,
            "spl": spl,
            "best_step": self.best_step,
            "best_spl": self.best_spl,
        }
        scripted.save(str(path), _extra_files={"bgrl_meta.json": json.dumps(meta)})
        return path
