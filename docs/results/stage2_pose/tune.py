"""Bandwidth screen of categorical_pose (and categorical_kernel) on tuning seeds, rows as hf-sweep's.

Usage (from the repository root):
    PYTHONPATH=. python docs/results/stage2_pose/tune.py OUT.json C SEEDS METHOD:SETTING=V,...;...
e.g. ``tune_c06.json 0.6 100-109 "categorical_pose:kernel_position_bandwidth=0.3,kernel_heading_bandwidth=0.35"``.
Seeds 100-109 are tuning seeds: the reported tables use seeds 0-19. Rows already in OUT.json
(same task, C, seed, method and settings) are kept and not re-run.
"""

import functools
import json
import os
import sys
from multiprocessing import get_context


def one(args):
    import torch

    torch.set_num_threads(1)
    import services.learner.runs as runs
    from services.learner.feedback import FeedbackConfig
    from services.learner.runs import HFPolicySpec, hf_policy_run

    task, c, seed, method, settings = args
    runs.FeedbackConfig = functools.partial(FeedbackConfig, **settings)
    row = hf_policy_run(HFPolicySpec(task, c, seed, 1000, method))
    row["settings"] = settings
    print(task, c, seed, method, settings, row["greedy_spl"], row["sampled_success_rate"],
          round(row["wall_seconds"]), flush=True)
    return row


def parse_variant(text):
    method, _, rest = text.partition(":")
    settings = {}
    for item in filter(None, rest.split(",")):
        name, value = item.split("=")
        settings[name] = float(value)
    return method, settings


def key(row):
    return (row["task"], row["accuracy"], row["seed"], row["method"],
            json.dumps(row["settings"], sort_keys=True))


if __name__ == "__main__":
    out, c, seeds, variants = sys.argv[1], float(sys.argv[2]), sys.argv[3], sys.argv[4]
    first, last = (int(s) for s in seeds.split("-"))
    rows = json.load(open(out))["runs"] if os.path.exists(out) else []
    done = {key(r) for r in rows}
    jobs = [
        (t, c, s, m, st)
        for m, st in map(parse_variant, variants.split(";"))
        for s in range(first, last + 1)
        for t in ("sssg", "vssg")
        if (t, c, s, m, json.dumps(st, sort_keys=True)) not in done
    ]
    with get_context("spawn").Pool(2) as pool:
        for row in pool.imap_unordered(one, jobs):
            rows.append(row)
            with open(out, "w") as f:
                json.dump({"runs": rows}, f, indent=1)
