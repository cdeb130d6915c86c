"""Stage-3 stabilisers at C = 0.6, exploratory (docs/reproduction.md): the table of the arms.

Per arm, task and method (rl_sparse, hf_sparse): runs reaching SPL 0.7 (Wilson 95 %),
last-five and final SPL means (bootstrap 95 %), median steps to 0.7, collapses (an
evaluation >= 0.7 followed by one < 0.3) and the runs with one, the last-five mean of the
runs that reached 0.7 by 30k steps (keeping, not finding) and the best SPL; per arm and task
the paired acceleration (hf vs rl on the same seed: faster / slower seeds, one-sided Wilcoxon on the
censored steps, as H1 of docs/protocol.md); per arm, task and method the paired change
against the first arm (the baseline): last-five difference (bootstrap 95 %) and seeds that
reach 0.7 sooner / later. Statistics from services.learner.stats and .confirmatory.

Usage (from the repository root):
    PYTHONPATH=. python docs/results/stab3/analyse.py base=docs/results/stab3/base \
        anneal=docs/results/stab3/anneal ... > docs/results/stab3/analysis.md
"""

import itertools
import json
import sys
from pathlib import Path

import numpy as np

from services.learner.confirmatory import (
    censored_steps,
    count_estimate,
    last_five,
    mean_estimate,
    wilcoxon_fewer_steps,
)
from services.learner.outputs import load_results

METHODS = ("rl_sparse", "hf_sparse")
TASKS = ("sssg", "vssg")
KEPT_BY = 30_000
"""Runs that reached 0.7 by this step (before the last-five window, 32k-40k): their last-five
mean measures keeping, not finding, the goal."""


def collapses(curve):
    spls = [spl for _, spl in curve]
    return sum(1 for a, b in itertools.pairwise(spls) if a >= 0.7 and b < 0.3)


def cells(folder):
    out = {}
    for run in load_results(Path(folder) / "results.json").runs:
        out.setdefault((run.task, run.method), {})[run.seed] = run
    return out


def row(arm, task, method, runs):
    reach = count_estimate("reach", sum(r.steps_to_0_7 is not None for r in runs), len(runs))
    tails = mean_estimate("last5", [last_five(r) for r in runs])
    finals = mean_estimate("final", [r.final_spl for r in runs])
    steps = [r.steps_to_0_7 for r in runs if r.steps_to_0_7 is not None]
    falls = [collapses(r.curve) for r in runs]
    early = [last_five(r) for r in runs if r.steps_to_0_7 is not None and r.steps_to_0_7 <= KEPT_BY]
    return {
        "arm": arm,
        "task": task,
        "method": method,
        "n": len(runs),
        "reach": reach.k,
        "reach_ci": [reach.low, reach.high],
        "last5": tails.value,
        "last5_ci": [tails.low, tails.high],
        "final": finals.value,
        "final_ci": [finals.low, finals.high],
        "median_steps": float(np.median(steps)) if steps else None,
        "collapses": sum(falls),
        "runs_with_collapse": sum(f > 0 for f in falls),
        "kept_n": len(early),
        "kept_last5": float(np.mean(early)) if early else None,
        "best": float(np.mean([max(s for _, s in r.curve) for r in runs])),
    }


def paired(a, b):
    """(a faster, a slower, Wilcoxon p that a needs fewer steps) over the common seeds."""
    seeds = sorted(set(a) & set(b))
    sa = [censored_steps(a[s]) for s in seeds]
    sb = [censored_steps(b[s]) for s in seeds]
    faster = sum(x < y for x, y in zip(sa, sb, strict=True))
    slower = sum(x > y for x, y in zip(sa, sb, strict=True))
    return faster, slower, wilcoxon_fewer_steps(sa, sb)


def main(args):
    arms = [arg.split("=", 1) for arg in args]
    data = {name: cells(folder) for name, folder in arms}
    base_name = arms[0][0]
    rows, accel, change = [], [], []
    for name, _ in arms:
        for task in TASKS:
            for method in METHODS:
                runs = [data[name][(task, method)][s] for s in sorted(data[name][(task, method)])]
                rows.append(row(name, task, method, runs))
                if name != base_name:
                    cur, base = data[name][(task, method)], data[base_name][(task, method)]
                    seeds = sorted(set(cur) & set(base))
                    diff = [last_five(cur[s]) - last_five(base[s]) for s in seeds]
                    d = mean_estimate("diff", diff)
                    sooner, later, _ = paired(cur, base)
                    change.append(
                        {
                            "arm": name,
                            "task": task,
                            "method": method,
                            "n": len(seeds),
                            "last5_diff": d.value,
                            "last5_diff_ci": [d.low, d.high],
                            "sooner": sooner,
                            "later": later,
                        }
                    )
            faster, slower, p = paired(
                data[name][(task, "hf_sparse")], data[name][(task, "rl_sparse")]
            )
            accel.append(
                {
                    "arm": name,
                    "task": task,
                    "hf_faster": faster,
                    "hf_slower": slower,
                    "wilcoxon_p": p,
                }
            )
    print(
        "| arm | task | method | runs reaching 0.7 [Wilson 95 %] | last-5 SPL [bootstrap 95 %] "
        "| final SPL [bootstrap 95 %] | median steps to 0.7 | collapses (runs) "
        "| last-5 of the runs at 0.7 by 30k | best SPL |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        med = "-" if r["median_steps"] is None else f"{r['median_steps']:.0f}"
        kept = "-" if r["kept_n"] == 0 else f"{r['kept_last5']:.2f} ({r['kept_n']} runs)"
        print(
            f"| {r['arm']} | {r['task'].upper()} | {r['method']} | {r['reach']}/{r['n']} "
            f"[{r['reach_ci'][0]:.2f}, {r['reach_ci'][1]:.2f}] | {r['last5']:.2f} "
            f"[{r['last5_ci'][0]:.2f}, {r['last5_ci'][1]:.2f}] | {r['final']:.2f} "
            f"[{r['final_ci'][0]:.2f}, {r['final_ci'][1]:.2f}] | {med} | "
            f"{r['collapses']} ({r['runs_with_collapse']}) | {kept} | {r['best']:.2f} |"
        )
    print(
        "\n| arm | task | hf_sparse faster / slower than rl_sparse (seeds) | one-sided Wilcoxon p |"
    )
    print("|---|---|---|---|")
    for a in accel:
        print(
            f"| {a['arm']} | {a['task'].upper()} | {a['hf_faster']} / {a['hf_slower']} | "
            f"{a['wilcoxon_p']:.3g} |"
        )
    print(
        f"\n| arm vs {base_name} | task | method | last-5 difference, paired [bootstrap 95 %] | "
        "reaches 0.7 sooner / later (seeds) |"
    )
    print("|---|---|---|---|---|")
    for c in change:
        print(
            f"| {c['arm']} | {c['task'].upper()} | {c['method']} | {c['last5_diff']:+.2f} "
            f"[{c['last5_diff_ci'][0]:+.2f}, {c['last5_diff_ci'][1]:+.2f}] | "
            f"{c['sooner']} / {c['later']} |"
        )
    Path(__file__).with_name("analysis.json").write_text(
        json.dumps({"rows": rows, "acceleration": accel, "change": change}, indent=1) + "\n"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
