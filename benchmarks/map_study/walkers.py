"""Wall-averse walker variants on one map: .venv/bin/python benchmarks/map_study/walkers.py MAP"""

import json
import sys

from services.sim.metrics import wall_averse_policy_success_rate

path = sys.argv[1]
episodes = int(sys.argv[2]) if len(sys.argv) > 2 else 3000
for task in ("sssg", "vssg"):
    for p, c in ((1 / 3, 0.7), (0.6, 0.7), (0.6, 1.0)):
        r = wall_averse_policy_success_rate(
            task, episodes=episodes, seed=0, map_path=path, forward_probability=p, min_clearance=c
        )
        row = {"map": path, "task": task, "p_forward": round(p, 2), "min_clearance": c}
        row |= {"successes": r.successes, "success_rate": r.success_rate}
        print(json.dumps(row | {"collision_rate": r.collision_rate}), flush=True)
