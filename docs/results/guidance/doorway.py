"""Where a run's robot goes: per 5000 training steps, the share of steps in the right-hand
room (x > 4.6 m) and aligned with the doorway (heading 0, 6.7 < y < 7.0, 3.0 < x < 3.7), the
0.5 m cells visited and the largest x. RL-sparse with the platform preset's PPO settings
(self-imitation on), default map.

Usage (from the repository root):
PYTHONPATH=. python docs/results/guidance/doorway.py TASK SEED [EXPLORE_COEF]
e.g. ``sssg 8`` (a failing run of reproduction.md, "A count-based exploration bonus").
"""

import math
import sys

import numpy as np

from services.learner.ppo import Callback, PPOConfig, train
from services.learner.specs import TASK_ENV_IDS


class PoseRecorder(Callback):
    def __init__(self) -> None:
        self.poses: list[tuple[float, float, float]] = []

    def on_step(self, global_step: int, info: dict) -> bool:
        self.poses.append(info["pose"])
        return True


if __name__ == "__main__":
    task, seed = sys.argv[1], int(sys.argv[2])
    explore_coef = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
    recorder = PoseRecorder()
    config = PPOConfig(
        env_id=TASK_ENV_IDS[task], seed=seed, sil_coef=1.0, explore_coef=explore_coef
    )
    result = train(config, recorder)
    poses = np.array(recorder.poses)
    for start in range(0, len(poses), 5000):
        x, y, yaw = poses[start : start + 5000].T
        aligned = (x > 3.0) & (x < 3.7) & (np.abs(yaw) < 0.1) & (y > 6.7) & (y < 7.0)
        cells = len({(math.floor(a / 0.5), math.floor(b / 0.5)) for a, b in zip(x, y)})
        print(
            f"steps {start:6d}+: right-hand room {np.mean(x > 4.6):.3f}, aligned with the "
            f"doorway {aligned.mean():.4f}, cells {cells}, largest x {x.max():.2f}"
        )
    print(
        "successful training episodes", sum(e[2] for e in result.episodes),
        "last five evaluations", [spl for _, spl in result.curve[-5:]],
    )  # fmt: skip
