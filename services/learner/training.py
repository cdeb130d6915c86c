"""What :func:`services.learner.ppo.train` takes and gives besides its config.

:class:`Callback` (progress hooks that can stop training, SB3 style), :class:`TrainResult`
and the TorchScript export of a trained policy (:class:`PolicyExport`).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

if TYPE_CHECKING:
    from services.learner.ppo import ActorCritic, PPOConfig


class PolicyExport(nn.Module):
    """What TorchScript export contains: normalisation + actor. ``forward`` gives logits."""

    def __init__(self, agent: ActorCritic) -> None:  # any module giving (logits, value)
        super().__init__()
        self.agent = agent

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Action logits for raw (unnormalised) observations, one or a batch."""
        logits, _ = self.agent(obs)
        return logits

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

    @property
    def final_spl(self) -> float:
        """SPL at the last evaluation."""
        return self.curve[-1][1]

    def act(self, obs: np.ndarray) -> int:
        """Greedy action of the trained policy."""
        with torch.no_grad():
            logits, _ = self.agent(torch.as_tensor(np.asarray(obs, dtype=np.float32)))
        return int(torch.argmax(logits))

    def export_torchscript(self, path: str | Path) -> Path:
        """Save normalisation + actor as TorchScript (``torch.jit.load`` needs no project)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with warnings.catch_warnings():  # TorchScript is deprecated but still the format
            warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.load reads anywhere
            scripted = torch.jit.script(PolicyExport(self.agent).eval())
        meta = {"config": asdict(self.config), "final_spl": self.final_spl}
        scripted.save(str(path), _extra_files={"bgrl_meta.json": json.dumps(meta)})
        return path
