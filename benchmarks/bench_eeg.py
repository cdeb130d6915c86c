"""EEG decoding benchmarks (``bgrl bench eeg``) and the quality -> accuracy sweep.

All data here is SYNTHETIC (virtual subject, :mod:`services.eeg.virtual.subject`).

* Decision latency: a recording is replayed over a loopback LSL stream (chunks of 32
  samples, paced at ``speed`` x real time) into :class:`services.eeg.live.ingest.LiveIngest`; for
  each action the latency runs from the moment the chunk holding the last sample of the
  [0, 0.8] s window is pushed to the moment P(error) is available (LSL transport, integrity
  checks, causal preprocessing, epoch cut, EEGNet). Peer, same run and same windows: MNE's
  offline path (``Raw.filter`` 1-40 Hz FIR, ``Raw.resample`` to 128 Hz, ``Epochs``) on the
  window plus the 5 s before it.
* Offline preprocessing speed of a 64 ch 2048 Hz recording, as a multiple of real time.
  Peer: ``mne.io.Raw.filter(1, 40)`` + ``Raw.resample(128)`` on the same data.
* Classifier training time on 600 epochs; peer: the 600 x 1.5 s calibration session.
* Peak memory (RSS) of ``bgrl subject simulate``, ``bgrl eeg calibrate`` and the EEG
  service's reading, validation and preprocessing of a recording, each in its own child
  process (``os.wait4`` reports the child's ``ru_maxrss``), for a ``minutes`` long
  64-channel 2048 Hz recording.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

import services.core
from services.core.actions import ACTION_PERIOD_S
from services.eeg.decoding.training_config import DECODERS

LSL_LOOPBACK_CFG = Path(services.core.__file__).with_name("lsl_loopback.cfg")
DEFAULT_QUALITIES = (0.0, 0.2, 0.3, 0.4, 0.6, 1.0)
LSL_CHUNK_SAMPLES = 32
"""Samples per LSL chunk in the replay (15.6 ms at 2048 Hz, a typical amplifier block)."""
MNE_PEER_CONTEXT_S = 5.0
"""Seconds of data before the window that the MNE peer filters (its FIR is ~3.3 s long)."""


def random_labels(n_actions: int, error_rate: float, seed: int) -> np.ndarray:
    """Oracle-like labels (True = correct) with errors drawn at random."""
    rng = np.random.default_rng(seed)
    return rng.random(n_actions) >= error_rate


def _percentiles(values_s: list[float]) -> dict[str, float]:
    v = np.asarray(values_s) * 1e3
    return {
        "p50_ms": float(np.percentile(v, 50)),
        "p99_ms": float(np.percentile(v, 99)),
        "max_ms": float(v.max()),
        "n": int(v.size),
    }


# ----------------------------------------------------------------------------- quality sweep


SWEEP_METRICS = ("test_accuracy", "balanced_accuracy", "roc_auc")


@functools.lru_cache(maxsize=1)
def _subject_epochs(seed: int, n_actions: int, error_rate: float) -> tuple[Any, Any, np.ndarray]:
    """The epochs of virtual subject ``seed`` simulated at quality 0 and 1, and its labels.
    Kept for the last subject: a serial sweep runs its two tasks (halves of the levels) one
    after the other, and the second reuses the first's simulations (read only)."""
    from services.eeg.recordings.epochs import epochs_from_raw
    from services.eeg.virtual.subject import simulate_recording

    labels = random_labels(n_actions, error_rate, seed)
    e0 = epochs_from_raw(simulate_recording(labels, quality=0.0, seed=seed))
    e1 = epochs_from_raw(simulate_recording(labels, quality=1.0, seed=seed))
    return e0, e1, labels


def _sweep_subject(
    seed: int,
    levels: list[float],
    n_actions: int,
    error_rate: float,
    check_linearity: bool,
    max_passes: int,
    decoders: tuple[str, ...] = DECODERS,
) -> list[dict[str, Any]]:
    """Calibrate one virtual subject (``seed``) at every quality level.

    Every decoder of ``decoders`` is trained on the same split; a row has the kept one's
    test metrics and, under ``decoders``, each one's.

    The generator is linear in ``quality`` (only the label-dependent components scale, the
    background does not depend on it), and so is the preprocessing. The epochs at level
    ``q`` are therefore ``X(0) + q * (X(1) - X(0))`` from two simulations; levels above 1
    extrapolate the generator (ErrP amplitudes times ``q``) to show how much stronger the
    clearest subject would have to be. ``check_linearity`` compares the construction with
    a direct simulation at quality 0.5.
    """
    import torch

    from services.eeg.decoding.calibration import TrainingConfig, train_classifier
    from services.eeg.recordings.epochs import EpochSet, epochs_from_raw
    from services.eeg.virtual.subject import simulate_recording

    torch.set_num_threads(1)
    e0, e1, labels = _subject_epochs(seed, n_actions, error_rate)
    delta = e1.X - e0.X
    linearity = None
    if check_linearity:
        direct = epochs_from_raw(simulate_recording(labels, quality=0.5, seed=seed)).X
        linearity = float(np.abs(direct - (e0.X + 0.5 * delta)).max() / np.abs(direct).max())
    rows = []
    for q in levels:
        t0 = time.perf_counter()
        X = (e0.X + np.float32(q) * delta).astype(np.float32)
        epochs = EpochSet(X, e0.y, e0.ch_names, e0.params, e0.sfreq_in, synthetic=True)
        config = TrainingConfig(max_passes=max_passes, decoders=decoders)
        m = train_classifier(epochs, seed=seed, config=config).metrics
        rows.append(
            {
                "quality": q,
                "seed": seed,
                "extrapolated": q > 1.0,
                "decoder": m["decoder"],
                "test_accuracy": m["test_accuracy"],
                "balanced_accuracy": m["balanced_accuracy"],
                "roc_auc": m["roc_auc"],
                "decoders": {
                    name: {key: d[key] for key in (*SWEEP_METRICS, "val_accuracy")}
                    for name, d in m["decoders"].items()
                },
                "n_epochs": m["n_epochs"],
                "n_test": m["n_test"],
                "best_pass": m.get("best_pass"),
                "seconds": time.perf_counter() - t0,
                "linearity_check_max_rel_diff": linearity,
            }
        )
    return rows


def quality_sweep(
    levels: list[float],
    *,
    n_seeds: int = 5,
    n_actions: int = 600,
    error_rate: float = 0.3,
    max_passes: int = 150,
    jobs: int = 1,
    partial_path: Path | None = None,
    decoders: tuple[str, ...] = DECODERS,
) -> dict[str, Any]:
    """Calibrate ``n_seeds`` virtual subjects at every quality level; summarise test metrics
    of the kept decoder and of each decoder (``decoders``, trained on the same split).

    Each seed is a different virtual subject (background, topography, latency shift) and
    also seeds the labels, the split and the training. Levels above 1 are extrapolations
    (see :func:`_sweep_subject`). ``partial_path`` receives the runs so far after every
    task, so a long sweep that is stopped keeps its finished part.
    """
    from tqdm import tqdm

    from services.core.files import write_results_json

    # Two tasks per subject (each half of the levels) balance the work over the workers.
    halves = [list(levels[: (len(levels) + 1) // 2]), list(levels[(len(levels) + 1) // 2 :])]
    tasks = [
        (s, half, n_actions, error_rate, s == 0 and k == 0, max_passes, tuple(decoders))
        for s in range(n_seeds)
        for k, half in enumerate(h for h in halves if h)
    ]
    runs: list[dict[str, Any]] = []

    def collect(rows: list[dict[str, Any]]) -> None:
        runs.extend(rows)
        if partial_path is not None:
            write_results_json(partial_path, runs, indent=1)

    if jobs == 1:
        for task in tqdm(tasks, desc="quality sweep", unit="task"):
            collect(_sweep_subject(*task))
        _subject_epochs.cache_clear()
    else:
        with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(_sweep_subject, *task) for task in tasks]
            for future in tqdm(as_completed(futures), total=len(futures), desc="quality sweep"):
                collect(future.result())
    return summarize_sweep(
        runs,
        levels,
        n_seeds=n_seeds,
        n_actions=n_actions,
        error_rate=error_rate,
        max_passes=max_passes,
        decoders=decoders,
    )


def summarize_sweep(
    runs: list[dict[str, Any]],
    levels: list[float],
    *,
    n_seeds: int,
    n_actions: int,
    error_rate: float,
    max_passes: int,
    decoders: tuple[str, ...],
) -> dict[str, Any]:
    """The sweep's JSON from its runs (also from a stopped sweep's
    ``quality_sweep.partial.json``): per level, mean and SD over the subjects that ran
    (``n_seeds`` of each level says how many) of the kept decoder's and every decoder's
    test metrics, and how often each was kept."""
    summary = []
    for q in levels:
        rows = [r for r in runs if r["quality"] == q]
        if not rows:
            continue
        entry: dict[str, Any] = {"quality": q, "extrapolated": q > 1.0, "n_seeds": len(rows)}
        entry.update(_mean_std(rows))
        entry["decoders"] = {
            name: _mean_std([r["decoders"][name] for r in rows]) for name in decoders
        }
        entry["kept"] = {name: sum(r["decoder"] == name for r in rows) for name in decoders}
        entry["subjects"] = sorted(r["seed"] for r in rows)
        summary.append(entry)
    return {
        "synthetic": True,
        "n_actions": n_actions,
        "error_rate": error_rate,
        "n_seeds": n_seeds,
        "max_passes": max_passes,
        "decoders": list(decoders),
        "linearity_check_max_rel_diff": next(
            (
                r["linearity_check_max_rel_diff"]
                for r in runs
                if r["linearity_check_max_rel_diff"] is not None
            ),
            None,
        ),
        "summary": summary,
        "runs": runs,
    }


def _mean_std(rows: list[dict[str, Any]]) -> dict[str, float]:
    """``<metric>_mean`` and ``<metric>_std`` (ddof 1) of the sweep metrics over rows."""
    entry = {}
    for key in SWEEP_METRICS:
        values = np.array([r[key] for r in rows])
        entry[f"{key}_mean"] = float(values.mean())
        entry[f"{key}_std"] = float(values.std(ddof=1)) if len(rows) > 1 else 0.0
    return entry


def format_sweep_table(result: dict[str, Any]) -> str:
    """Markdown table per quality: test accuracy, balanced accuracy, ROC AUC (mean +- std)
    of every decoder, and how often each was kept."""
    names = result.get("decoders", ["eegnet"])
    header = [f"{name} {label}" for name in names for label in ("test acc.", "bal. acc.", "AUC")]
    lines = [
        "| quality | subjects | " + " | ".join(header) + " | kept |",
        "|---:|---:|" + "---:|" * len(header) + "---|",
    ]
    for e in result["summary"]:
        cells = [
            f"{e['decoders'][name][f'{k}_mean']:.3f} ± {e['decoders'][name][f'{k}_std']:.3f}"
            for name in names
            for k in SWEEP_METRICS
        ]
        kept = ", ".join(f"{name} {n}" for name, n in e["kept"].items())
        level = f"{e['quality']:.2f}" + (" (extrapolated)" if e["extrapolated"] else "")
        lines.append(f"| {level} | {e['n_seeds']} | " + " | ".join(cells) + f" | {kept} |")
    return "\n".join(lines)


def sweep_csv_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per quality and decoder (and ``kept``: the decoder calibration kept), with
    mean and SD over subjects of the test metrics and how often the decoder was kept."""
    rows = []
    for e in result["summary"]:
        groups = [(name, e["decoders"][name], e["kept"][name]) for name in result["decoders"]]
        groups.append(("kept", {k: e[k] for k in e if k.endswith(("_mean", "_std"))}, None))
        for name, stats, kept in groups:
            rows.append(
                {
                    "quality": e["quality"],
                    "extrapolated": e["extrapolated"],
                    "decoder": name,
                    "n_subjects": e["n_seeds"],
                    **{
                        f"{k}_{s}": stats[f"{k}_{s}"]
                        for k in SWEEP_METRICS
                        for s in ("mean", "std")
                    },
                    "times_kept": kept if kept is not None else "",
                }
            )
    return rows


def plot_sweep(result: dict[str, Any]):
    """Test accuracy and balanced accuracy (mean +- SD over subjects) against quality for
    every decoder and the kept one, and how often each decoder was kept."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from services.eeg.decoding.report import DECODER_NAMES

    names = list(result["decoders"])
    summary = result["summary"]
    q = np.array([e["quality"] for e in summary])
    fig = Figure(figsize=(15, 4.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    n_subjects = max(e["n_seeds"] for e in summary)
    fig.suptitle(
        f"SYNTHETIC virtual subjects: decoders on the same splits ({n_subjects} subjects, "
        f"{result['n_actions']} actions, {result['error_rate']:.0%} errors; "
        "mean ± SD over subjects)"
    )
    offsets = np.linspace(-0.012, 0.012, len(names) + 1)
    for ax, metric, title in zip(
        axes[:2],
        ("test_accuracy", "balanced_accuracy"),
        ("Held-out test accuracy", "Held-out balanced accuracy"),
        strict=True,
    ):
        for k, name in enumerate(names):
            mean = np.array([e["decoders"][name][f"{metric}_mean"] for e in summary])
            std = np.array([e["decoders"][name][f"{metric}_std"] for e in summary])
            ax.errorbar(q + offsets[k], mean, std, marker="o", capsize=3, label=DECODER_NAMES[name])
        mean = np.array([e[f"{metric}_mean"] for e in summary])
        std = np.array([e[f"{metric}_std"] for e in summary])
        ax.errorbar(
            q + offsets[-1],
            mean,
            std,
            color="k",
            ls="--",
            marker="s",
            capsize=3,
            label="kept on validation",
        )
        chance = 0.5 if metric == "balanced_accuracy" else 1.0 - result["error_rate"]
        ax.axhline(
            chance,
            color="0.6",
            lw=0.8,
            ls=":",
            label="always 'correct'" if metric == "test_accuracy" else "chance",
        )
        ax.set(xlabel="virtual subject quality", ylabel=metric.replace("_", " "), title=title)
        ax.legend(fontsize=8)
    ax = axes[2]
    bottom = np.zeros(len(summary))
    width = 0.6 * float(np.min(np.diff(q))) if len(q) > 1 else 0.1
    for name in names:
        counts = np.array([e["kept"][name] for e in summary], dtype=float)
        ax.bar(q, counts, width, bottom=bottom, label=DECODER_NAMES[name])
        bottom += counts
    ax.set(
        xlabel="virtual subject quality",
        ylabel="subjects",
        title="Kept by calibration (best validation accuracy)",
        yticks=range(n_subjects + 1),
    )
    ax.legend(fontsize=8)
    return fig


def write_sweep_outputs(result: dict[str, Any], out: Path) -> list[Path]:
    """``quality_sweep.json``, ``.csv`` (:func:`sweep_csv_rows`) and ``.png``
    (:func:`plot_sweep`) in ``out``; returns their paths."""
    import csv

    from services.core.files import write_results_json

    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"quality_sweep.{ext}" for ext in ("json", "csv", "png")]
    write_results_json(paths[0], result)
    rows = sweep_csv_rows(result)
    with paths[1].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_sweep(result).savefig(paths[2], dpi=100)
    return paths


# ----------------------------------------------------------------------------- benchmarks


def bench_training(n_actions: int = 600, seed: int = 0) -> tuple[dict[str, Any], Any]:
    """Time calibration training on ``n_actions`` epochs; returns (figures, classifier)."""
    from services.eeg.decoding.calibration import train_classifier
    from services.eeg.recordings.epochs import epochs_from_raw
    from services.eeg.virtual.subject import simulate_recording

    raw = simulate_recording(random_labels(n_actions, 0.3, seed), quality=0.4, seed=seed)
    epochs = epochs_from_raw(raw)
    t0, c0 = time.perf_counter(), time.process_time()
    result = train_classifier(epochs, seed=seed)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    session_s = n_actions * ACTION_PERIOD_S
    m = result.metrics
    figures = {
        "n_epochs": m["n_epochs"],
        "passes_run": m["passes_run"],
        "train_seconds": seconds,
        "train_cpu_seconds": cpu,
        "seconds_per_pass": seconds / m["passes_run"],
        "peer_session_seconds": session_s,
        "session_over_train_ratio": session_s / seconds,
        "test_accuracy": m["test_accuracy"],
    }
    return figures, result.classifier


def bench_offline_speed(minutes: float = 20.0, seed: int = 1) -> dict[str, Any]:
    """Offline preprocessing of a ``minutes`` long recording: ours vs MNE filter+resample."""
    import mne

    from services.eeg.signal.preprocessing import OnlinePreprocessor, PreprocessingParams
    from services.eeg.virtual.subject import simulate_recording

    n_actions = int(minutes * 60 / ACTION_PERIOD_S) - 2
    raw = simulate_recording(random_labels(n_actions, 0.3, seed), quality=0.5, seed=seed)
    duration_s = raw.n_times / raw.info["sfreq"]
    sfreq = raw.info["sfreq"]
    picks = mne.pick_types(raw.info, eeg=True)
    ch_names = [raw.ch_names[i] for i in picks]
    chunk = round(4.0 * sfreq)

    t0, c0 = time.perf_counter(), time.process_time()
    pre = OnlinePreprocessor(ch_names, sfreq, PreprocessingParams())
    for start in range(0, raw.n_times, chunk):
        pre.push(raw._data[picks, start : start + chunk].T, start / sfreq)
    ours_s, ours_cpu = time.perf_counter() - t0, time.process_time() - c0

    raw.pick(picks)
    t0, c0 = time.perf_counter(), time.process_time()
    raw.filter(1.0, 40.0, n_jobs=1, verbose=False)
    raw.resample(128.0, n_jobs=1, verbose=False)
    mne_s, mne_cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "recording_seconds": duration_s,
        "n_channels": len(ch_names),
        "sfreq": sfreq,
        "ours_seconds": ours_s,
        "ours_x_realtime": duration_s / ours_s,
        "mne_seconds": mne_s,
        "mne_x_realtime": duration_s / mne_s,
        "ours_over_mne_speed_ratio": mne_s / ours_s,
        "ours_cpu_seconds": ours_cpu,
        "ours_x_realtime_cpu": duration_s / ours_cpu,
        "mne_cpu_seconds": mne_cpu,
        "mne_x_realtime_cpu": duration_s / mne_cpu,
    }


def _mne_peer_decision(raw_data: np.ndarray, info: Any, onset_sample: int, classifier) -> float:
    """MNE's offline path for one window (filter, resample, epoch, classify); returns P."""
    import mne

    sfreq = info["sfreq"]
    start = max(0, onset_sample - round(MNE_PEER_CONTEXT_S * sfreq))
    stop = onset_sample + round(0.85 * sfreq)
    seg = mne.io.RawArray(raw_data[:, start:stop], info, verbose=False)
    seg.filter(1.0, 40.0, n_jobs=1, verbose=False)
    seg.resample(128.0, n_jobs=1, verbose=False)
    onset = round((onset_sample - start) / sfreq * 128.0)
    events = np.array([[onset, 0, 2]])
    ep = mne.Epochs(seg, events, tmin=0.0, tmax=0.8, baseline=None, preload=True, verbose=False)
    return float(classifier.predict_proba(ep.get_data(copy=False))[0])


def bench_latency(
    classifier, n_actions: int = 500, speed: float = 3.0, seed: int = 2, n_peer: int = 100
) -> dict[str, Any]:
    """Decision latency over a live loopback LSL replay of ``n_actions`` actions."""
    import mne
    import torch

    os.environ.setdefault("LSLAPICFG", str(LSL_LOOPBACK_CFG))  # stay on this machine
    from mne_lsl.lsl import StreamInfo, StreamInlet, StreamOutlet, resolve_streams

    from services.eeg.live.ingest import LiveIngest
    from services.eeg.recordings.epochs import epochs_from_raw
    from services.eeg.virtual.subject import simulate_recording

    torch.set_num_threads(1)
    period = 1.0
    raw = simulate_recording(
        random_labels(n_actions, 0.3, seed), quality=1.0, seed=seed, action_period_s=period
    )
    sfreq = raw.info["sfreq"]
    picks = mne.pick_types(raw.info, eeg=True)
    ch_names = [raw.ch_names[i] for i in picks]
    classifier.check_compatible(ch_names, sfreq)
    data = np.ascontiguousarray(raw.get_data(picks=picks).T, dtype=np.float32)
    stim = raw.get_data(picks="Status")[0]
    onset_samples = np.flatnonzero(np.diff(stim, prepend=0) > 0)
    n_win = round(0.8 * sfreq)

    name = f"bench-eeg-{time.time_ns()}"
    info = StreamInfo(name, "EEG", len(ch_names), sfreq, "float32", name)
    info.set_channel_names(ch_names)
    outlet = StreamOutlet(info, chunk_size=LSL_CHUNK_SAMPLES)
    streams = resolve_streams(timeout=5.0, name=name)
    if not streams:
        raise RuntimeError("loopback LSL stream not found")
    inlet = StreamInlet(streams[0], max_buffered=60)
    inlet.open_stream(timeout=5.0)

    n_chunks = int(np.ceil(data.shape[0] / LSL_CHUNK_SAMPLES))
    push_wall = np.full(n_chunks, np.nan)
    t0_stream = 1000.0
    done = threading.Event()

    def produce() -> None:
        start = time.perf_counter()
        for k in range(n_chunks):
            due = start + k * LSL_CHUNK_SAMPLES / sfreq / speed
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            chunk = data[k * LSL_CHUNK_SAMPLES : (k + 1) * LSL_CHUNK_SAMPLES]
            # A float timestamp is the last sample's; liblsl spaces the others by 1 / sfreq.
            last = k * LSL_CHUNK_SAMPLES + len(chunk) - 1
            push_wall[k] = time.perf_counter()  # before the push: the consumer may be faster
            outlet.push_chunk(chunk, timestamp=t0_stream + last / sfreq)
        done.set()

    ingest = LiveIngest(ch_names, sfreq, params=classifier.params)
    onsets = t0_stream + onset_samples / sfreq
    latencies, compute, online_p, decided, rejected = [], [], [], [], []
    next_action = 0
    producer = threading.Thread(target=produce, daemon=True)
    producer.start()
    try:
        while next_action < len(onsets):
            chunk, stamps = inlet.pull_chunk(timeout=0.0, max_samples=4096)
            if len(stamps) == 0:
                if done.is_set() and inlet.samples_available == 0:
                    break
                time.sleep(0.0005)
                continue
            t_pulled = time.perf_counter()
            ingest.push_chunk(chunk, stamps)
            while next_action < len(onsets):
                answer = ingest.epoch_for(float(onsets[next_action]))
                if answer.status == "pending":
                    break
                if answer.status == "rejected":
                    rejected.append(answer.reason)
                    next_action += 1
                    continue
                p = float(classifier.predict_proba(answer.epoch)[0])
                t_done = time.perf_counter()
                last_sample = onset_samples[next_action] + n_win
                latencies.append(t_done - push_wall[last_sample // LSL_CHUNK_SAMPLES])
                compute.append(t_done - t_pulled)
                online_p.append(p)
                decided.append(next_action)
                next_action += 1
    finally:
        producer.join(timeout=5.0)
        inlet.close_stream()

    offline = epochs_from_raw(raw, classifier.params)
    offline_p = classifier.predict_proba(offline.X[decided])
    peer_latencies = []
    eeg_info = mne.pick_info(raw.info, picks)
    raw_eeg = raw.get_data(picks=picks)
    for onset_sample in onset_samples[5 : 5 + n_peer]:
        t0 = time.perf_counter()
        _mne_peer_decision(raw_eeg, eeg_info, int(onset_sample), classifier)
        peer_latencies.append(time.perf_counter() - t0)
    ours, peer = _percentiles(latencies), _percentiles(peer_latencies)
    return {
        "n_actions": len(latencies),
        "n_rejected": len(rejected),
        "rejection_reasons": sorted(set(rejected))[:5],
        "stream_issues": [issue.kind for issue in ingest.issues][:20],
        "replay_speed": speed,
        "action_period_s": period,
        "lsl_chunk_samples": LSL_CHUNK_SAMPLES,
        "ours": ours,
        "ours_compute_after_pull": _percentiles(compute),
        "mne_peer": peer,
        "peer_over_ours_p50_ratio": peer["p50_ms"] / ours["p50_ms"],
        "online_vs_offline_max_abs_p_diff": float(np.max(np.abs(np.array(online_p) - offline_p))),
    }


# ----------------------------------------------------------------------------- memory

MEMORY_LIMIT_MB = 1500.0
"""Peak RSS each EEG step must stay under for a 20-minute 64-channel 2048 Hz recording."""

_SERVICE_READ = """
import sys
from services.eeg.recordings.io import action_events, file_sha256, read_recording
from services.eeg.signal.preprocessing import epochs_from_raw
raw = read_recording(sys.argv[1])  # upload: validate, count the actions, hash
events = action_events(raw)
file_sha256(sys.argv[1])
epochs = epochs_from_raw(read_recording(sys.argv[1]))  # job: the epochs it trains on
print(len(events), epochs.X.shape)
"""


_AS_OTHER_SOFTWARE = """
import sys, zipfile
from pathlib import Path
import mne, pybv
from services.eeg.recordings.io import action_events, read_recording
raw, out = read_recording(sys.argv[1]), Path(sys.argv[2])
events = action_events(raw)
eeg = [c for c, kind in zip(raw.ch_names, raw.get_channel_types()) if kind == "eeg"]
data = raw.get_data(picks=eeg)
onsets = events[:, 0] - raw.first_samp
pybv.write_brainvision(  # BrainVision: float32 samples, the actions as stimulus markers
    data=data, sfreq=raw.info["sfreq"], ch_names=eeg, fname_base="upload", folder_out=out,
    events=[{"onset": int(s), "description": int(c)} for s, c in zip(onsets, events[:, 2])],
    unit="µV",
)
with zipfile.ZipFile(out / "upload.zip", "w", compression=zipfile.ZIP_DEFLATED) as archive:
    for suffix in ("vhdr", "vmrk", "eeg"):
        archive.write(out / f"upload.{suffix}", f"upload.{suffix}")
        (out / f"upload.{suffix}").unlink()
plain = mne.io.RawArray(data, mne.create_info(eeg, raw.info["sfreq"], "eeg"), verbose="error")
del data
codes = [str(code) for code in events[:, 2]]
plain.set_annotations(mne.Annotations(onsets / raw.info["sfreq"], 0.0, codes))
mne.export.export_raw(out / "upload.set", plain, fmt="eeglab", verbose="error")  # eeglabio
"""
"""The recording as other software writes it: a zipped BrainVision set (pybv) with the
actions as markers, and an EEGLAB dataset (``mne.export``: samples inside the ``.set``)."""


def peak_rss_mb(command: list[str]) -> tuple[float, float]:
    """Run ``command`` in a child process; (its peak RSS in MB, wall seconds).

    ``os.wait4`` returns the rusage of that child alone (``ru_maxrss`` in KiB on Linux).
    Raises ``RuntimeError`` with the child's stderr tail if it fails.
    """
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        if child.returncode != 0:
            err.seek(0)
            tail = err.read().decode(errors="replace")[-2000:]
            raise RuntimeError(f"{command[:4]} failed ({child.returncode}):\n{tail}")
    return usage.ru_maxrss / 1024.0, time.perf_counter() - t0


def bench_memory(minutes: float = 20.0, max_passes: int = 20, seed: int = 0) -> dict[str, Any]:
    """Peak RSS of simulate, calibrate and the service's reading of a ``minutes`` recording.

    Each step runs as the user runs it, in a fresh child process: ``bgrl subject simulate
    --actions N`` (N actions of 1.5 s fill ``minutes``), ``bgrl eeg calibrate`` on that
    file (``--max-passes`` bounds the training time; memory does not grow with passes),
    and the EEG service's path (``read_recording`` + ``action_events`` + sha256 at upload,
    ``read_recording`` + ``epochs_from_raw`` in the job) on that BDF, and on the recording
    as a zipped BrainVision set with markers and as an EEGLAB dataset
    (``_AS_OTHER_SOFTWARE``, a setup step).
    """
    n_actions = round(minutes * 60 / ACTION_PERIOD_S) - 2
    bgrl = [sys.executable, "-m", "services.cli.main"]
    with tempfile.TemporaryDirectory(prefix="bgrl-bench-memory-") as tmp:
        recording = str(Path(tmp) / "subject.bdf")
        steps = {
            "simulate": [
                *bgrl,
                *("subject", "simulate", "--actions", str(n_actions), "--seed", str(seed)),
                *("--out", recording),
            ],
            "calibrate": [
                *bgrl,
                *("eeg", "calibrate", recording, "--out", str(Path(tmp) / "classifier")),
                *("--max-passes", str(max_passes), "--seed", str(seed)),
            ],
            "service_read_and_preprocess": [sys.executable, "-c", _SERVICE_READ, recording],
            # setup: the two files below (this step's memory is the converter's, not ours)
            "as_other_software": [sys.executable, "-c", _AS_OTHER_SOFTWARE, recording, tmp],
            "service_brainvision_zip": [
                *(sys.executable, "-c", _SERVICE_READ, str(Path(tmp) / "upload.zip"))
            ],
            "service_eeglab_set": [
                *(sys.executable, "-c", _SERVICE_READ, str(Path(tmp) / "upload.set"))
            ],
        }
        figures: dict[str, Any] = {}
        for step, command in steps.items():
            peak, seconds = peak_rss_mb(command)
            figures[step] = {"peak_rss_mb": peak, "wall_seconds": seconds}
        figures["recording_mb"] = Path(recording).stat().st_size / 2**20
    return {
        "minutes": minutes,
        "n_actions": n_actions,
        "n_channels": 64,
        "sfreq": 2048.0,
        "max_passes": max_passes,
        "limit_mb": MEMORY_LIMIT_MB,
        **figures,
    }


def run_benchmark(
    n_actions: int = 500, speed: float = 3.0, offline_minutes: float = 20.0
) -> dict[str, Any]:
    """All EEG decoding benchmarks; returns the JSON-ready result with a ``summary``."""
    import torch

    torch.set_num_threads(1)
    memory = bench_memory(offline_minutes)
    training, classifier = bench_training()
    latency = bench_latency(classifier, n_actions=n_actions, speed=speed)
    offline = bench_offline_speed(offline_minutes)
    return {
        "synthetic": True,
        "summary": {
            "peak_rss_mb_simulate": memory["simulate"]["peak_rss_mb"],
            "peak_rss_mb_calibrate": memory["calibrate"]["peak_rss_mb"],
            "peak_rss_mb_service_read": memory["service_read_and_preprocess"]["peak_rss_mb"],
            "peak_rss_mb_service_brainvision_zip": memory["service_brainvision_zip"]["peak_rss_mb"],
            "peak_rss_mb_service_eeglab_set": memory["service_eeglab_set"]["peak_rss_mb"],
            "decision_latency_p50_ms": latency["ours"]["p50_ms"],
            "decision_latency_p99_ms": latency["ours"]["p99_ms"],
            "mne_peer_latency_p50_ms": latency["mne_peer"]["p50_ms"],
            "offline_x_realtime": offline["ours_x_realtime"],
            "offline_x_realtime_cpu": offline["ours_x_realtime_cpu"],
            "mne_offline_x_realtime": offline["mne_x_realtime"],
            "train_seconds_600_epochs": training["train_seconds"],
            "train_cpu_seconds_600_epochs": training["train_cpu_seconds"],
        },
        "memory": memory,
        "latency": latency,
        "offline_preprocessing": offline,
        "training": training,
    }
