"""Per seed, the channels side by side: the first budget with a useful pi_HF (greedy SPL
>= 0.5) and the first from which it stays useful at every larger budget measured.

Usage (from the repository root): ``PYTHONPATH=. python docs/results/nstar_soft/paired.py
docs/results/nstar_soft/nstar_rows.json [docs/results/nstar_soft/recalibrated/nstar_rows.json]``;
the second file's soft rows count as the channel ``soft_recalibrated``. Prints one markdown
table per (method, task, C) and each channel against the hard one.
"""

from __future__ import annotations

import sys
from collections import defaultdict

from services.learner.nstar import load_rows

USEFUL = 0.5


def first_useful(points: list[tuple[int, float]]) -> tuple[int | None, int | None]:
    """(first useful budget, first budget from which every larger one is useful)."""
    points = sorted(points)
    first = next((n for n, spl in points if spl >= USEFUL), None)
    stays = None
    for n, spl in reversed(points):
        if spl < USEFUL:
            break
        stays = n
    return first, stays


def load(paths: list[str]) -> list[dict]:
    rows = []
    for k, path in enumerate(paths):
        for row in load_rows(path).rows:
            if k:
                row = {**row, "label_channel": f"{row['label_channel']}_recalibrated"}
            rows.append(row)
    return rows


def main(paths: list[str]) -> None:
    series: dict[tuple, dict[str, dict[int, list]]] = defaultdict(lambda: defaultdict(dict))
    for r in load(paths):
        key = (r["method"], r["task"], r["decoder_accuracy_target"])
        series[key][r["label_channel"]].setdefault(r["seed"], []).append(
            (r["n_labels"], r["greedy_spl"])
        )
    for (method, task, c), channels in sorted(series.items()):
        names = sorted(channels)
        seeds = sorted(set.intersection(*(set(channels[n]) for n in names)))
        if len(names) < 2 or not seeds:
            continue
        print(f"\n{method} {task.upper()} decoder target {c:g}: first useful / stays useful\n")
        print("| seed | " + " | ".join(names) + " |")
        print("|---" * (len(names) + 1) + "|")
        stays = {n: {} for n in names}
        for seed in seeds:
            cells = []
            for n in names:
                pair = first_useful(channels[n][seed])
                stays[n][seed] = pair[1] if pair[1] is not None else float("inf")
                cells.append(" / ".join("-" if v is None else str(v) for v in pair))
            print(f"| {seed} | " + " | ".join(cells) + " |")
        for n in names:
            if n == "hard" or "hard" not in stays:
                continue
            earlier = sum(stays[n][s] < stays["hard"][s] for s in seeds)
            later = sum(stays[n][s] > stays["hard"][s] for s in seeds)
            print(
                f"\n{n} stays useful earlier than hard on {earlier}, later on {later}, "
                f"tied on {len(seeds) - earlier - later} of {len(seeds)} seeds"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
