"""Peak resident memory of one lockstep batch of a Fig. 3 sweep (every run in one process).

``python -m benchmarks.sweep_memory --seeds 10 --steps 1024`` trains the runs of
``bgrl reproduce``'s defaults for 10 seeds (100 runs, 60 of them HF+sparse with stage 2 in
lockstep) as one batch (:func:`services.learner.runs.run_lockstep`, no cap on its size) and
prints, as JSON, the process's resident memory before and its peak during the batch
(sampled every 50 ms), with the wall and CPU seconds. A run's memory does not grow with its
budget beyond its per-update metrics, so a short budget gives the peak of a full one.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from benchmarks.bench_sweep import PeakMemory, sweep_specs
from services.learner.runs import RunRecord, run_lockstep


def measure(seeds: int, steps: int) -> dict[str, object]:
    """Train the sweep's runs as one lockstep batch; its memory and times."""
    torch.set_num_threads(1)
    specs = sweep_specs(seeds, steps)
    memory = PeakMemory()
    wall, cpu = time.perf_counter(), time.process_time()
    with memory.watch():
        outcomes = run_lockstep(specs)
    return {
        "runs": len(specs),
        "steps_per_run": steps,
        "succeeded": sum(isinstance(o, RunRecord) for o in outcomes),
        "rss_before_gb": memory.start_bytes / 1e9,
        "peak_rss_gb": memory.peak_bytes / 1e9,
        "wall_seconds": time.perf_counter() - wall,
        "cpu_seconds": time.process_time() - cpu,
        "load_average": os.getloadavg(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="10 runs a seed (default 10)")
    parser.add_argument("--steps", type=int, default=1024, help="env steps a run")
    args = parser.parse_args()
    print(json.dumps(measure(args.seeds, args.steps), indent=2))


if __name__ == "__main__":
    main()
