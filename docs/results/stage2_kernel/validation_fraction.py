"""Training on every label: categorical_kernel with Fhat's validation hold-out at 0.2 and 0.

Seeds 0-9, both tasks, 1000 labels, stage 2 alone, the hf-sweep's label streams and
evaluation. Usage (from the repository root):
PYTHONPATH=. python docs/results/stage2_kernel/validation_fraction.py C F1,F2 OUT.json [WORKERS]
e.g. ``0.6 0.2,0.0 validation_fraction_c0.6.json 2``.
"""

import json
import sys
from contextlib import closing
from multiprocessing import get_context

import gymnasium as gym
import numpy as np

from services.learner.evaluation import eval_seeds, evaluate_spl, run_episode
from services.learner.feedback import FeedbackConfig, collect_feedback
from services.learner.feedback_sources import OracleFeedbackSource
from services.learner.runs import N_HF_PROBE_EPISODES
from services.learner.seeding import RunSeeds, Stream, evaluation_reset_seeds
from services.learner.specs import N_VSSG_EVAL_STARTS, TASK_ENV_IDS


def one(args):
    task, seed, accuracy, fraction, n_labels = args
    with closing(gym.make(TASK_ENV_IDS[task], reward_mode="sparse")) as env:
        seeds = RunSeeds(seed)
        source = OracleFeedbackSource(accuracy, seed=seeds.int_seed(Stream.LABEL_NOISE))
        config = FeedbackConfig(
            method="categorical_kernel", good_accuracy=accuracy, bad_accuracy=accuracy,
            validation_fraction=fraction,
        )  # fmt: skip
        hf = collect_feedback(
            env, source, n_labels, config=config, seed=seeds.int_seed(Stream.LABEL_COLLECTION)
        )
        policy = hf.policy
        greedy = evaluate_spl(env, policy.act, eval_seeds(task, N_VSSG_EVAL_STARTS))
        rng = RunSeeds(seed).generator(Stream.HF_PROBE)
        sampled = [
            run_episode(env, lambda o: policy.act(o, rng), reset_seed)[0]
            for reset_seed in evaluation_reset_seeds(N_HF_PROBE_EPISODES)
        ]
    return {"task": task, "seed": seed, "acc": accuracy, "vf": fraction, "n": n_labels,
            "greedy": greedy, "sampled": float(np.mean(sampled))}  # fmt: skip


if __name__ == "__main__":
    accuracy, fractions = float(sys.argv[1]), [float(v) for v in sys.argv[2].split(",")]
    out, workers = sys.argv[3], int(sys.argv[4]) if len(sys.argv) > 4 else 1
    jobs = [(t, s, accuracy, f, 1000) for f in fractions for t in ("sssg", "vssg") for s in range(10)]
    with get_context("spawn").Pool(workers) as pool:
        rows = pool.map(one, jobs)
    with open(out, "w") as file:
        json.dump(rows, file)
    for fraction in fractions:
        for task in ("sssg", "vssg"):
            cell = [r for r in rows if r["vf"] == fraction and r["task"] == task]
            greedy = [r["greedy"] for r in cell]
            print(
                f"{task} validation_fraction={fraction}: greedy SPL {np.mean(greedy):.2f}, "
                f"useful {sum(g >= 0.5 for g in greedy)}/10, sampled success "
                f"{np.mean([r['sampled'] for r in cell]):.2f}, per seed {[round(g, 2) for g in greedy]}"
            )
