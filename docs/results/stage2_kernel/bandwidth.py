"""Bandwidth check of categorical_kernel: seeds 0-9, both tasks, 1000 labels, rows as hf-sweep's.

Usage (from the repository root): PYTHONPATH=. python docs/results/stage2_kernel/bandwidth.py
OUT.json C H1,H2,...   e.g. ``bandwidth_c06.json 0.6 0.2,0.05``. The default h (0.1) is
the hf-sweep rows in hf_policies.json.
"""

import functools
import json
import sys
from multiprocessing import get_context


def one(args):
    import torch

    torch.set_num_threads(1)
    import services.learner.runs as runs
    from services.learner.feedback import FeedbackConfig
    from services.learner.runs import HFPolicySpec, hf_policy_run

    task, c, seed, h = args
    runs.FeedbackConfig = functools.partial(FeedbackConfig, kernel_bandwidth=h)
    row = hf_policy_run(HFPolicySpec(task, c, seed, 1000, "categorical_kernel"))
    print(task, c, seed, h, row["greedy_spl"], round(row["wall_seconds"]), flush=True)
    return row


if __name__ == "__main__":
    out, c, bandwidths = sys.argv[1], float(sys.argv[2]), sys.argv[3].split(",")
    jobs = [(t, c, s, float(h)) for h in bandwidths for s in range(10) for t in ("sssg", "vssg")]
    with get_context("spawn").Pool(2) as pool:
        rows = pool.map(one, jobs, chunksize=1)
    with open(out, "w") as f:
        json.dump({"runs": rows, "failed": []}, f, indent=1)
