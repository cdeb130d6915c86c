"""``bgrl demo``: the whole closed loop with the virtual subject, through the real services.

calibration session (random policy, virtual subject) -> ``eeg_calibration`` job (classifier)
-> online session (pi_HF from the learner, labels decoded live by the EEG service) -> guided
PPO from the session's HF model. The sim, EEG and learner services are started as processes
(as ``bgrl up`` does) on free loopback ports with a temporary data folder unless
``--data-dir`` is given; the jobs run in this process with the worker's job runner (the same
handlers a ``bgrl worker`` runs). Writes ``OUT/summary.json`` and ``OUT/demo.png``.
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from services.cli.closed_loop import (
    add_job,
    cpu_seconds,
    job_runtime,
    lab_session,
    live_run,
    run_latencies,
    run_to_end,
    start_services,
)


def _plot(
    out: Path,
    curve: list[list[float]],
    hf_spl: float | None,
    accuracy_trace: list,
    baseline: list[list[float]] | None = None,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    if accuracy_trace:
        xs, ys = zip(*accuracy_trace, strict=True)
        left.plot(xs, ys)
    left.set_xlabel("labels")
    left.set_ylabel("running decoding accuracy (vs oracle)")
    left.set_ylim(0, 1)
    left.set_title("online session (virtual subject, SYNTHETIC)")
    if curve:
        steps, spl = zip(*curve, strict=True)
        right.plot(steps, spl, label="guided PPO")
    if baseline:
        steps, spl = zip(*baseline, strict=True)
        right.plot(steps, spl, label="RL-sparse, same seed", color="C3")
    if hf_spl is not None:
        right.axhline(hf_spl, linestyle="--", color="grey", label="pi_HF alone")
    right.axhline(0.7, linestyle=":", color="k", lw=0.8)
    right.set_xlabel("environment steps")
    right.set_ylabel("SPL")
    right.set_ylim(0, 1.08)  # room above 1.0: a curve at SPL 1 stays visible
    right.legend()
    right.set_title("guided PPO from the session's pi_HF")
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=100)
    plt.close(fig)


def _accuracy_trace(runtime: Any, run_id: int) -> list[tuple[int, float]]:
    from sqlalchemy import select

    from services.core.db.live import LiveDecision

    with runtime.sessions() as db:
        rows = db.execute(
            select(LiveDecision.feedback, LiveDecision.oracle_correct)
            .where(LiveDecision.run_id == run_id, LiveDecision.status == "ok")
            .order_by(LiveDecision.step)
        ).all()
    trace, hits = [], 0
    for n, (feedback, correct) in enumerate(rows, start=1):
        hits += (feedback == "correct") == bool(correct)
        trace.append((n, hits / n))
    return trace


def _rl_sparse_beside(guided_spec: dict[str, Any], seed: int) -> Any:
    """RL-sparse with the guided run's task, seed and PPO settings (the comparison the paper
    makes), run in this process."""
    from services.learner.runs import run_one
    from services.learner.specs import RunSpec

    spec = RunSpec(
        guided_spec["task"],
        "rl_sparse",
        seed,
        map_path=guided_spec.get("map_path"),
        ppo_overrides=guided_spec["ppo_overrides"],
    )
    return run_one(spec)


def demo(
    out: Annotated[Path, typer.Option(help="Folder for summary.json and demo.png.")],
    accelerated: Annotated[
        bool, typer.Option(help="Run on the virtual clock (else one action every 1.5 s).")
    ] = False,
    data_dir: Annotated[
        Path | None, typer.Option(help="Data folder (default: a temporary one).")
    ] = None,
    calibration_actions: Annotated[int, typer.Option(min=20)] = 600,
    labels: Annotated[int, typer.Option(min=1, help="Label budget of the online session.")] = 1000,
    quality: Annotated[float, typer.Option(min=0.0, max=1.0, help="Virtual subject.")] = 0.7,
    total_steps: Annotated[int, typer.Option(min=256, help="Guided-PPO env steps.")] = 40_000,
    max_passes: Annotated[int | None, typer.Option(min=1, help="Calibration passes.")] = None,
    seed: Annotated[int, typer.Option(min=0)] = 0,
) -> None:
    """Calibration -> classifier -> online session -> guided PPO, with the virtual subject."""
    from services.core.db.models import Subject
    from services.core.logging import configure_logging
    from services.learner.runs import steps_to_reach
    from services.platform.jobs import GUIDED_PPO
    from services.worker.calibration import eeg_calibration
    from services.worker.live_session import live_session
    from services.worker.training import guided_ppo

    configure_logging("WARNING")
    out.mkdir(parents=True, exist_ok=True)
    tmp = None if data_dir is not None else tempfile.TemporaryDirectory(prefix="bgrl-demo-")
    folder = (data_dir or Path(tmp.name)).resolve()  # type: ignore[union-attr]
    token = os.environ.get("BGRL_SERVICE_TOKEN") or secrets.token_hex(16)
    started = time.perf_counter()
    load_before = os.getloadavg()
    urls, children = start_services(folder, token)
    for name, url in urls.items():
        os.environ[f"BGRL_{name.upper()}_URL"] = url
    os.environ["BGRL_SERVICE_TOKEN"] = token
    os.environ["BGRL_DATA_DIR"] = str(folder)
    runtime = job_runtime(folder)
    stages: dict[str, float] = {"services_s": time.perf_counter() - started}
    try:
        with runtime.sessions() as db:
            subject = Subject(code=f"DEMO-{secrets.token_hex(3)}", notes="virtual subject")
            db.add(subject)
            db.commit()
            subject_id = subject.id
        common = {"accelerated": accelerated, "virtual_quality": quality, "seed": seed}

        t = time.perf_counter()
        typer.echo(f"calibration: {calibration_actions} actions")
        cal_session = lab_session(runtime, "calibration", subject_id)
        options = {**common, "n_actions": calibration_actions}
        if max_passes is not None:
            options["calibration_max_passes"] = max_passes
        _, job_id = live_run(runtime, cal_session, "calibration", options)
        calibration = run_to_end(runtime, job_id, live_session)
        stages["calibration_session_s"] = time.perf_counter() - t

        t = time.perf_counter()
        typer.echo("classifier: eeg_calibration job")
        trained = run_to_end(runtime, calibration["calibration_job_id"], eeg_calibration)
        stages["classifier_s"] = time.perf_counter() - t

        t = time.perf_counter()
        typer.echo(f"online session: {labels} labels")
        online_session = lab_session(runtime, "online", subject_id)
        options = {**common, "classifier_id": trained["classifier_id"], "label_budget": labels}
        run_id, job_id = live_run(runtime, online_session, "online", options)
        online = run_to_end(runtime, job_id, live_session)
        stages["online_session_s"] = time.perf_counter() - t

        t = time.perf_counter()
        typer.echo(f"guided PPO from HF model {online['hf_model_id']}: {total_steps} steps")
        guided = {"task": "sssg", "method": "hf_sparse", "hf_model_id": online["hf_model_id"],
                  "seed": seed, "total_steps": total_steps, "preset": "platform"}  # fmt: skip
        job_id = add_job(runtime, GUIDED_PPO.name, guided)
        trained_rl = run_to_end(runtime, job_id, guided_ppo)
        stages["guided_ppo_s"] = time.perf_counter() - t

        t = time.perf_counter()
        typer.echo(f"RL-sparse from the same seed and settings: {total_steps} steps")
        baseline = _rl_sparse_beside(trained_rl["spec"], seed)
        stages["rl_sparse_s"] = time.perf_counter() - t

        summary = {
            "synthetic": True,
            "accelerated": accelerated,
            "virtual_quality": quality,
            "calibration_actions": calibration["actions"],
            "classifier_test_accuracy": trained["metrics"].get("test_accuracy"),
            "live_decoding_accuracy": online["decoding_accuracy"],
            "labels": online["labels"],
            "online_actions": online["actions"],
            "rejected_epochs": online["decoding_rejected"],
            "hf_policy_spl": online["hf_policy_spl"],
            "label_channel": online["label_channel"],
            "guided_steps_to_0_7": steps_to_reach(trained_rl.get("curve", [])),
            "rl_sparse_steps_to_0_7": baseline.steps_to_0_7,
            "rl_sparse_final_spl": baseline.final_spl,
            "final_spl": trained_rl["final_spl"],
            "best_spl": trained_rl.get("best_spl"),
            "steps": total_steps,
            "guided_ppo_settings": {
                "preset": "platform",
                "hf_treatment": trained_rl["spec"]["hf_treatment"],
                **{
                    key: value
                    for key, value in trained_rl["spec"]["ppo_overrides"].items()
                    if key != "total_steps"
                },
            },
            "latency_ms": run_latencies(runtime, run_id),
            "wall_seconds": {**stages, "total_s": time.perf_counter() - started},
            "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
            "cpu_seconds": cpu_seconds(children),
            "cpus": os.cpu_count(),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        _plot(
            out,
            trained_rl.get("curve", []),
            online["hf_policy_spl"],
            _accuracy_trace(runtime, run_id),
            baseline.curve,
        )
        typer.echo(json.dumps({k: summary[k] for k in list(summary)[:18]}, indent=2))
        typer.echo(f"wrote {out / 'summary.json'} and {out / 'demo.png'}")
    finally:
        deadline = time.monotonic() + 10
        for child in children:
            child.terminate()
        for child in children:
            child.wait_or_kill(deadline)
        runtime.engine.dispose()
        if tmp is not None:
            tmp.cleanup()


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``demo`` to the ``bgrl`` command."""
    app.command("demo")(demo)
