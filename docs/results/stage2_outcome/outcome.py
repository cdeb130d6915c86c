"""Prototype: outcome evidence (collision -> not optimal, goal -> optimal) and a forward prior
for categorical_kernel at C, stage 2 alone. Cells "sure:goal:prior" (sure 0 = no outcome
evidence; goal g|n; prior 0 = none, else P(forward)).
Usage (from the repository root):
    PYTHONPATH=. python docs/results/stage2_outcome/outcome.py C CELLS FIRST-LAST OUT.json WORKERS [N_LABELS]
e.g. ``0.6 "0:n:0,0.95:g:0" 100-109 screen_c06.json 2``. Seeds 100-109 are tuning seeds. Rows
already in OUT.json (same task, seed, cell, labels) are kept and not re-run.
"""
import json, os, sys, time
from multiprocessing import get_context


def one(args):
    import numpy as np
    import torch
    torch.set_num_threads(1)
    import services.learner.runs as runs
    import services.learner.feedback as fb
    from services.learner.kernel_prior import KernelEvidence
    from services.learner.networks import ObsNormalizer
    from services.learner.runs import HFPolicySpec, hf_policy_run

    task, c, seed, sure, goal, prior, n_labels = args
    stats = {"collisions": 0, "goals": 0}

    if prior > 0:
        log_prior = np.log(np.array([prior, (1 - prior) / 2, (1 - prior) / 2]))
        def posterior(self, indices):
            return torch.softmax(torch.from_numpy(self.evidence[indices] + log_prior).float(), dim=-1)
        KernelEvidence.posterior = posterior

    def add_outcome(learner, obs, action, label):
        obs = np.asarray(obs, dtype=np.float32)
        k = learner.kernel
        x = learner.model.normalizer(torch.from_numpy(obs)).numpy()
        g, b = k.good, k.bad
        k.good, k.bad = sure, sure
        k.add(x, action, label)
        k.good, k.bad = g, b
        learner._step(None, torch.from_numpy(obs[None]), torch.tensor([int(action)]),
                      torch.tensor([float(label)]))
        learner.buffer.add(obs, action, label)
        for _ in range(learner.config.replay_updates):
            idx = learner.buffer.sample_indices(learner.rng, learner.config.batch_size,
                                                learner.config.newest_fraction)
            learner._step(idx, *learner.buffer.tensors(idx))

    def collect(env, source, n_labels=1000, *, config=None, seed=0, max_steps=None, on_label=None):
        start = time.perf_counter()
        learner = fb.FeedbackLearner(ObsNormalizer.from_space(env.observation_space), config, seed)
        rng = fb.sampling_rng(seed)
        obs, _ = env.reset(seed=seed)
        records, n_steps, n_episodes = [], 0, 1
        while len(records) < n_labels:
            action = learner.collection_action(obs, rng)
            optimal = fb._optimal_now(env, action)
            next_obs, _, term, trunc, info = env.step(action)
            n_steps += 1
            label = source.feedback(obs, action, optimal)
            if label is not None:
                records.append(learner.add(obs, action, label, optimal))
            if sure > 0 and info.get("collision"):
                stats["collisions"] += 1
                add_outcome(learner, obs, action, False)
            if sure > 0 and goal and info.get("is_success"):
                stats["goals"] += 1
                add_outcome(learner, obs, action, True)
            obs = next_obs
            if term or trunc:
                obs, _ = env.reset()
                n_episodes += 1
        known = [r for r in records if r.optimal is not None]
        acc = float(np.mean([r.label == r.optimal for r in known]))
        a_n, a_t = learner.validation_accuracy()
        return fb.HFResult(learner.model, learner.config, records, n_steps, n_episodes, a_n, a_t,
                           acc, time.perf_counter() - start)

    runs.collect_feedback = collect
    row = hf_policy_run(HFPolicySpec(task, c, seed, n_labels, "categorical_kernel"))
    row.update(cell=f"{sure}:{'g' if goal else 'n'}:{prior}", **stats)
    print(task, seed, row["cell"], round(row["greedy_spl"], 2), row["sampled_success_rate"],
          stats, round(row["wall_seconds"]), flush=True)
    return row


if __name__ == "__main__":
    c, cells, seeds, out, workers = float(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5])
    n_labels = int(sys.argv[6]) if len(sys.argv) > 6 else 1000
    first, last = (int(s) for s in seeds.split("-"))
    rows = json.load(open(out))["runs"] if os.path.exists(out) else []
    done = {(r["task"], r["seed"], r["cell"], r["n_labels"]) for r in rows}
    jobs = []
    for cell in cells.split(","):
        sure, goal, prior = cell.split(":")
        name = f"{float(sure)}:{goal}:{float(prior)}"
        for s in range(first, last + 1):
            for t in ("sssg", "vssg"):
                if (t, s, name, n_labels) not in done:
                    jobs.append((t, c, s, float(sure), goal == "g", float(prior), n_labels))
    with get_context("spawn").Pool(workers) as pool:
        for row in pool.imap_unordered(one, jobs):
            rows.append(row)
            with open(out, "w") as f:
                json.dump({"runs": rows}, f, indent=1)
