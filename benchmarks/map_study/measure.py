"""Map-study measurements (the measurements behind docs/map-study.md).

Usage: .venv/bin/python benchmarks/map_study/measure.py MAP.json [EPISODES]
Prints: oracle path (SSSG + 30 VSSG starts), monotone-distance check, straight-line crash,
rich-reward returns (crash / oracle), uniform and wall-averse walker success (SSSG).
"""

import itertools
import json
import math
import sys

from services.sim.env import BrainNavEnv
from services.sim.metrics import random_policy_success_rate, wall_averse_policy_success_rate

path = sys.argv[1]
episodes = int(sys.argv[2]) if len(sys.argv) > 2 else 3000
out: dict = {"map": path, "episodes": episodes}


def returns(env, actions, gamma=0.99):
    total = disc = 0.0
    for t, a in enumerate(actions):
        _, r, term, _, info = env.step(a)
        total += r
        disc += gamma**t * r
        if term:
            return total, disc, t + 1, info["is_success"], info["collision"]
    return total, disc, len(actions), False, False


env = BrainNavEnv(task="sssg", reward_mode="rich", map_path=path)
_, info = env.reset(seed=0)
out["sssg_path"] = info["shortest_path_steps"]
# oracle rollout through the env, distance monotone?
env.reset(seed=0)
ds, n = [], 0
while True:
    a = min(env.optimal_actions(), key=lambda a: (0, 1, 2).index(a))
    _, r, term, trunc, info = env.step(a)
    n += 1
    gx, gy = env.nav_map.goal.x, env.nav_map.goal.y
    px, py, _ = env.pose
    ds.append(math.hypot(gx - px, gy - py))
    if term or trunc or n > 60:
        break
out["oracle_success"] = bool(info["is_success"])
out["distance_never_increases"] = all(b <= a + 1e-9 for a, b in itertools.pairwise(ds))
env.reset(seed=0)
out["rich_crash_straight"] = returns(env, [0] * 120)
env.reset(seed=0)
# oracle return
seq = []
env.reset(seed=0)
tot = disc = 0.0
for t in range(120):
    a = min(env.optimal_actions(), key=lambda a: (0, 1, 2).index(a))
    _, r, term, _, info = env.step(a)
    tot += r
    disc += 0.99**t * r
    if term:
        break
out["rich_oracle"] = (tot, disc, t + 1, info["is_success"])
env.reset(seed=0)
out["rich_turn_in_place"] = returns(env, [1] * 120)[:3]
env.close()
venv = BrainNavEnv(task="vssg", map_path=path)
lens = [venv.reset(seed=s)[1]["shortest_path_steps"] for s in range(30)]
venv.close()
out["vssg_path_min_max"] = (min(lens), max(lens))
print(json.dumps(out), flush=True)
for name, fn, kw in (
    ("uniform", random_policy_success_rate, {}),
    ("averse_p0.33", wall_averse_policy_success_rate, {}),
    ("averse_p0.6", wall_averse_policy_success_rate, {"forward_probability": 0.6}),
):
    r = fn("sssg", episodes=episodes, seed=0, map_path=path, **kw)
    print(
        json.dumps(
            {
                "map": path,
                "walker": name,
                "successes": r.successes,
                "success_rate": r.success_rate,
                "collision_rate": r.collision_rate,
            }
        ),
        flush=True,
    )
