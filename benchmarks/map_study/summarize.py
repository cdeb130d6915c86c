"""Markdown tables for docs/map-study.md from results/map_study/*."""

import json
from pathlib import Path

import numpy as np

ROOT = Path("results/map_study")
MAPS = [
    "default",
    "candidate_pocket",
    "candidate_clutter",
    "candidate_narrow",
    "candidate_gate",
    "candidate_post",
    "candidate_empty",
]


def pct(x):
    return f"{100 * x:.2f} %"


def load_jsonl(path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


print(
    "| map | SSSG path | VSSG path (30 starts) | dist. never increases | straight crash at step "
    "| uniform | averse p=1/3, 1 m | "
    "averse p=0.6, 1 m | averse p=1/3, 0.7 m | averse p=0.6, 0.7 m |"
)
print("|---|---|---|---|---|---|---|---|---|---|")
for m in MAPS:
    short = m.removeprefix("candidate_")
    meas = load_jsonl(ROOT / f"measure_{short}.jsonl")
    walk = load_jsonl(ROOT / f"walkers_{m}.jsonl")
    head = next((r for r in meas if "sssg_path" in r), {})
    w = {r["walker"]: r for r in meas if "walker" in r}
    v = {(r["p_forward"], r["min_clearance"]): r for r in walk if r["task"] == "sssg"}

    def cell(r):
        return f"{pct(r['success_rate'])} ({r['successes']})" if r else "-"

    print(
        f"| {m} | {head.get('sssg_path', '-')} | {head.get('vssg_path_min_max', '-')} | "
        f"{head.get('distance_never_increases', '-')} | "
        f"{head.get('rich_crash_straight', [None] * 3)[2]} | {cell(w.get('uniform'))} | "
        f"{cell(w.get('averse_p0.33'))} | {cell(w.get('averse_p0.6') or v.get((0.6, 1.0)))} | "
        f"{cell(v.get((0.33, 0.7)))} | {cell(v.get((0.6, 0.7)))} |"
    )
print()
print(
    "| map | method | SSSG final SPL per seed (0, 1, ...) | mean ± std | max SPL at any eval "
    "| training successes (episodes) | collision rate, last 2k steps |"
)
print("|---|---|---|---|---|---|---|")
for m in MAPS:
    f = ROOT / m / "results.json"
    if not f.exists():
        continue
    runs = json.loads(f.read_text())["runs"]
    for method in ("rl_sparse", "rl_rich"):
        rs = sorted((r for r in runs if r["method"] == method), key=lambda r: r["seed"])
        if not rs:
            continue
        finals = [r["final_spl"] for r in rs]
        peak = [max(s for _, s in r["curve"]) for r in rs]
        succ = [
            sum(
                round(w["success_rate"] * w["episodes"])
                for w in r["training_episodes"]
                if w["episodes"]
            )
            for r in rs
        ]
        eps = [r["n_episodes"] for r in rs]
        last = [r["training_episodes"][-1]["collision_rate"] for r in rs]
        print(
            f"| {m} | {method} | {' / '.join(f'{x:.2f}' for x in finals)} | "
            f"{np.mean(finals):.2f} ± {np.std(finals):.2f} (n={len(rs)}) | "
            f"{' / '.join(f'{x:.2f}' for x in peak)} | "
            f"{' / '.join(f'{s} ({e})' for s, e in zip(succ, eps, strict=True))} | "
            f"{' / '.join(f'{x:.2f}' if x is not None else '-' for x in last)} |"
        )
