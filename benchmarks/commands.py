"""``bgrl bench ...`` and ``bgrl eeg quality-sweep``: the commands that run the benchmarks.

They sit above the CLI (benchmarks > cli in the import contract): the ``bgrl`` entry point
(:mod:`services.cli.main`, the composition root) adds them with :func:`register`.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Annotated

import typer
from tqdm import tqdm

from services.cli.eeg import eeg_app
from services.cli.paths import output_folder
from services.eeg.decoding.training_config import DECODERS


def bench_sim(
    out: Annotated[Path, typer.Option(help="Folder for sim.json.")],
    env_steps: Annotated[int, typer.Option(min=100, help="Env steps measured in total.")] = 20_000,
    rounds: Annotated[int, typer.Option(min=1, help="Interleaved env/ray-cast rounds.")] = 10,
    frames: Annotated[int, typer.Option(min=1, help="Frames rendered.")] = 60,
    oracle_queries: Annotated[int, typer.Option(min=1, help="Oracle queries timed.")] = 2_000,
    service_steps: Annotated[int, typer.Option(min=1, help="Steps through the HTTP app.")] = 300,
    seed: Annotated[int, typer.Option(min=0, help="Seed of actions and query poses.")] = 0,
) -> None:
    """Sim costs against peers in the same run; writes OUT/sim.json.

    Env steps/s vs raw rayTestBatch, frame and top-down render times, oracle build and
    query times, HTTP step overhead.
    """
    from benchmarks import bench_sim as bench
    from services.core.files import write_results_json

    output_folder(out)  # before the minutes of measuring
    total = rounds + math.ceil(frames / 10) + 3
    with tqdm(total=total, desc="bench sim", unit="part") as bar:

        def progress(message: str) -> None:
            bar.set_postfix_str(message)
            bar.update(1)

        started = time.perf_counter()
        result = bench.run(
            env_steps=env_steps,
            rounds=rounds,
            frames=frames,
            oracle_queries=oracle_queries,
            service_steps=service_steps,
            seed=seed,
            progress=progress,
        )
    result["command"] = (
        f"bgrl bench sim --out {out} --env-steps {env_steps} --rounds {rounds} "
        f"--frames {frames} --oracle-queries {oracle_queries} --service-steps {service_steps} "
        f"--seed {seed}"
    )
    path = write_results_json(out / "sim.json", result)
    env, render, oracle, service = (
        result["env_step"],
        result["render"],
        result["oracle"],
        result["service"],
    )
    typer.echo(
        f"env {env['env_steps_per_s']:.0f} steps/s vs rayTestBatch "
        f"{env['raycast_batches_per_s']:.0f}/s: ratio {env['ratio_env_to_raycast']:.2f} "
        f"(aim >= {env['aim_ratio']})\n"
        f"frame 320x240 {render['camera_frame_ms']['mean']:.1f} ms, top-down "
        f"{render['top_down_ms']['mean']:.1f} ms\n"
        f"oracle build {oracle['build_cold_s']:.2f} s (cache load {oracle['cache_load_s']:.2f} s), "
        f"query {oracle['optimal_actions_us']:.0f} us (optimal actions), "
        f"{oracle['cost_to_go_us']:.0f} us (cost-to-go)\n"
        f"HTTP step {service['http_step_ms']:.2f} ms vs GET /health "
        f"{service['http_health_ms']:.2f} ms vs direct env step "
        f"{service['direct_env_step_ms']:.3f} ms\n"
        f"wrote {path} in {time.perf_counter() - started:.0f} s"
    )


def quality_sweep_command(
    out: Annotated[Path, typer.Option(help="Folder for quality_sweep.json, .csv and .png.")] = Path(
        "benchmarks/results"
    ),
    qualities: Annotated[
        list[float] | None,
        typer.Option(
            "--quality",
            min=0.0,
            help="Quality levels (repeatable); above 1 extrapolates the generator's ErrP.",
        ),
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, help="Subjects (seeds) per quality level.")] = 5,
    actions: Annotated[int, typer.Option(min=60, help="Actions per calibration session.")] = 600,
    error_rate: Annotated[float, typer.Option(min=0.05, max=0.95)] = 0.3,
    max_passes: Annotated[int, typer.Option(min=1, help="Training passes cap per run.")] = 150,
    jobs: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 1,
    decoders: Annotated[
        str,
        typer.Option(
            help="Comma-separated decoders trained on each split (eegnet, lda, xdawn_rg)."
        ),
    ] = ",".join(DECODERS),
) -> None:
    """Simulate and calibrate virtual subjects per quality level: every decoder on the same
    splits; writes quality_sweep.json, .csv and .png and prints the table."""
    from benchmarks.bench_eeg import (
        DEFAULT_QUALITIES,
        format_sweep_table,
        quality_sweep,
        write_sweep_outputs,
    )
    from services.eeg.decoding.calibration import TrainingConfig

    names = tuple(d.strip() for d in decoders.split(",") if d.strip())
    try:
        TrainingConfig(decoders=names)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--decoders") from exc
    output_folder(out)
    result = quality_sweep(
        qualities or list(DEFAULT_QUALITIES),
        n_seeds=seeds,
        n_actions=actions,
        error_rate=error_rate,
        max_passes=max_passes,
        jobs=jobs,
        partial_path=out / "quality_sweep.partial.json",
        decoders=names,
    )
    paths = write_sweep_outputs(result, out)
    typer.echo(format_sweep_table(result))
    typer.echo("wrote " + ", ".join(str(p) for p in paths))


def bench_eeg(
    out: Annotated[Path, typer.Option(help="Folder for eeg.json.")] = Path("benchmarks/results"),
    actions: Annotated[int, typer.Option(min=10, help="Actions in the live LSL replay.")] = 500,
    speed: Annotated[float, typer.Option(min=0.5, help="Replay speed (x real time).")] = 3.0,
    minutes: Annotated[
        float, typer.Option(min=0.5, help="Recording length for the offline and memory figures.")
    ] = 20.0,
    memory_only: Annotated[
        bool,
        typer.Option(
            "--memory-only", help="Only the peak-memory figures (writes eeg_memory.json)."
        ),
    ] = False,
) -> None:
    """Peak memory of simulate / calibrate / service reading, decision latency (live LSL
    replay), offline preprocessing speed, training time."""
    from benchmarks.bench_eeg import bench_memory, run_benchmark
    from services.core.files import finite_or_null, write_results_json

    output_folder(out)
    if memory_only:
        memory = bench_memory(minutes)
        path = write_results_json(out / "eeg_memory.json", memory)
        typer.echo(json.dumps(finite_or_null(memory), indent=2))
        typer.echo(f"wrote {path}")
        return
    result = run_benchmark(n_actions=actions, speed=speed, offline_minutes=minutes)
    path = write_results_json(out / "eeg.json", result)
    typer.echo(json.dumps(result["summary"], indent=2))
    typer.echo(f"wrote {path}")


def bench_learner(
    out: Annotated[Path, typer.Option(help="Output folder; writes learner.json.")],
    steps: Annotated[
        int, typer.Option(min=256, help="Env steps per throughput measurement.")
    ] = 4096,
    target_steps: Annotated[
        int, typer.Option(min=2000, help="Budget of the time-to-0.7-SPL runs.")
    ] = 40_000,
    target_seeds: Annotated[
        int, typer.Option(min=1, help="Seeds per method of the time-to-0.7-SPL runs.")
    ] = 3,
) -> None:
    """PPO throughput vs Stable-Baselines3, Fhat update rate, HF+sparse time to 0.7 SPL."""
    from benchmarks.bench_learner import run_benchmark

    output_folder(out)
    result = run_benchmark(out, steps=steps, target_steps=target_steps, target_seeds=target_seeds)
    typer.echo(json.dumps(result["figures"], indent=1))


def bench_sweep(
    out: Annotated[Path, typer.Option(help="Output folder; writes sweep.json.")],
    seeds: Annotated[
        int, typer.Option(min=1, help="Seeds of the Fig. 3 sweep (10 runs a seed).")
    ] = 2,
    steps: Annotated[int, typer.Option(min=256, help="Env steps per run.")] = 4096,
    sb3_runs: Annotated[
        int, typer.Option(min=1, help="RL runs of the sweep also trained by SB3 PPO.")
    ] = 2,
) -> None:
    """One sweep three ways in one process: runs alone, in lockstep, and SB3 PPO.

    Runs per CPU-hour, env steps per CPU-second and the ratios; the full Fig. 3 (100 runs x
    40k steps) extrapolated on 2 cores; peak memory. Writes OUT/sweep.json.
    """
    from benchmarks.bench_sweep import PARTS, run
    from services.core.files import write_results_json

    output_folder(out)  # before the minutes of measuring
    with tqdm(total=PARTS, desc="bench sweep", unit="part") as bar:

        def progress(message: str) -> None:
            bar.set_postfix_str(message)
            bar.update(1)

        result = run(seeds=seeds, steps=steps, sb3_runs=sb3_runs, progress=progress)
    result["command"] = (
        f"bgrl bench sweep --out {out} --seeds {seeds} --steps {steps} --sb3-runs {sb3_runs}"
    )
    write_results_json(out / "sweep.json", result, indent=1)
    typer.echo(json.dumps(result["figures"], indent=1))


def bench_sb3_peer(
    out: Annotated[Path, typer.Option(help="Output folder; writes sb3_peer.json, summary.md.")],
    tasks: Annotated[str, typer.Option(help="Comma-separated: sssg,vssg.")] = "vssg",
    methods: Annotated[
        str, typer.Option(help="Comma-separated methods whose reward SB3 learns from.")
    ] = "rl_rich",
    seeds: Annotated[int, typer.Option(min=1, help="Seeds per task and method.")] = 5,
    first_seed: Annotated[int, typer.Option(min=0, help="First seed.")] = 0,
    steps: Annotated[int, typer.Option(min=2048, help="Env steps per run.")] = 150_000,
    eval_every: Annotated[int, typer.Option(min=1, help="Env steps between evaluations.")] = 10_000,
    stop_when_held: Annotated[
        int, typer.Option(min=0, help="Stop a run after this many evaluations >= 0.7 (0: never).")
    ] = 0,
    workers: Annotated[int, typer.Option(min=1, help="Runs at a time.")] = 2,
    reward_scale: Annotated[
        float, typer.Option(min=0.0, help="Factor on SB3's rewards (default: our PPO's).")
    ] = 0.01,
) -> None:
    """Stable-Baselines3 PPO with its defaults on our env, per method's reward: SPL curves.

    Resumes: runs already in OUT/sb3_peer.json are kept. Writes summary.md and
    sb3_peer_<task>.png beside it.
    """
    from benchmarks.sb3_peer import run

    output_folder(out)
    task_list = [t.strip() for t in tasks.split(",") if t.strip()]
    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    seed_list = list(range(first_seed, first_seed + seeds))
    with tqdm(total=len(task_list) * len(method_list) * seeds, desc="sb3 peer", unit="run") as bar:

        def progress(message: str) -> None:
            bar.set_postfix_str(message)
            bar.update(1)

        try:
            run(
                out,
                tasks=task_list,
                methods=method_list,
                seeds=seed_list,
                total_steps=steps,
                eval_every=eval_every,
                stop_when_held=stop_when_held or None,
                workers=workers,
                reward_scale=reward_scale,
                progress=progress,
            )
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None
    typer.echo((out / "summary.md").read_text())


def bench_api(
    out: Annotated[Path, typer.Option(help="Folder for api.json.")],
    rate: Annotated[float, typer.Option(min=1, help="Requests/s of each route.")] = 200.0,
    light_rate: Annotated[
        float, typer.Option(min=1, help="Requests/s of the second, lighter load.")
    ] = 25.0,
    duration: Annotated[float, typer.Option(min=1, help="Seconds of load per route.")] = 30.0,
    blocks: Annotated[int, typer.Option(min=1, help="Alternating blocks per route.")] = 6,
    jobs_stored: Annotated[int, typer.Option(min=50, help="Jobs in the database.")] = 1000,
    batch: Annotated[
        int, typer.Option(min=1, help="Throughput jobs per worker in each phase.")
    ] = 2,
    probes: Annotated[int, typer.Option(min=1, help="Queue-latency probe jobs per phase.")] = 5,
    job_method: Annotated[
        str, typer.Option(help="Method of the throughput jobs (rl_sparse, rl_rich, hf_sparse).")
    ] = "hf_sparse",
    job_steps: Annotated[int, typer.Option(min=128, help="total_steps of each job.")] = 2000,
    jobs: Annotated[bool, typer.Option(help="Also measure job throughput (slow).")] = True,
    api_workers: Annotated[
        int | None,
        typer.Option(
            min=1,
            max=64,
            help="Api processes under the read load (default: as `bgrl up` runs them on "
            "each database: 1 on SQLite, one per core up to 4 on PostgreSQL).",
        ),
    ] = None,
) -> None:
    """Api reads under load (SQLite, PostgreSQL) vs a bare route, each load level on a
    fresh api; CPU per request in process; api RSS; job throughput with 1 and 2 workers
    and queue latency; writes OUT/api.json."""
    import time

    from tqdm import tqdm

    from benchmarks import bench_api as bench

    with tqdm(desc="bench api", unit="part") as bar:

        def progress(message: str) -> None:
            bar.set_postfix_str(message)
            bar.update(1)

        started = time.perf_counter()
        result = bench.run(
            rate=rate,
            light_rate=light_rate,
            duration_s=duration,
            blocks=blocks,
            jobs_stored=jobs_stored,
            batch=batch,
            probes=probes,
            job_method=job_method,
            job_steps=job_steps,
            jobs=jobs,
            api_workers=api_workers,
            progress=progress,
        )
    result["command"] = (
        f"bgrl bench api --out {out} --rate {rate:g} --light-rate {light_rate:g} "
        f"--duration {duration:g} --blocks {blocks} "
        f"--jobs-stored {jobs_stored} --batch {batch} --probes {probes} "
        f"--job-method {job_method} --job-steps {job_steps}"
        f"{'' if api_workers is None else f' --api-workers {api_workers}'}"
        f"{'' if jobs else ' --no-jobs'}"
    )
    out.mkdir(parents=True, exist_ok=True)
    path = out / "api.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    for name, reads in result["reads"].items():
        if "skipped" in reads:
            typer.echo(f"{name}: skipped ({reads['skipped']})")
            continue
        for level in (reads["load"], reads["light_load"]):
            jobs_route, bare = (level["routes"][r] for r in (bench.LIST, bench.BARE))
            ratio = level["list_p99_to_bare_p99"]
            typer.echo(
                f"{name} at {level['rate_per_s']:g} req/s: GET {bench.JOBS_ROUTE} p50 "
                f"{jobs_route['p50_ms']:.1f} ms p99 {jobs_route['p99_ms']:.1f} ms "
                f"({jobs_route['errors']} errors) vs the bare route's p50 "
                f"{bare['p50_ms']:.1f} ms p99 {bare['p99_ms']:.1f} ms ({bare['errors']} "
                f"errors); p99 ratio {'-' if ratio is None else f'{ratio:.2f}'}; aim met: "
                f"{level['meets_aim']}; api RSS {level['api_rss_mb']['idle']:.0f} -> "
                f"{level['api_rss_mb']['after_load']:.0f} MiB"
            )
        cpu = reads["cpu_ms_per_request_in_process"]
        typer.echo(
            f"{name}: CPU per request in process: "
            + f"list {cpu['list']:.2f} ms, bare {cpu['bare']:.2f} ms "
            + f"(ratio {cpu['list_to_bare']:.1f})"
        )
    tp = result["throughput"]
    if tp is None:
        typer.echo(f"wrote {path} in {time.perf_counter() - started:.0f} s")
        return
    typer.echo(
        f"jobs/min: 1 worker {tp['workers_1']['jobs_per_minute']:.1f}, 2 workers "
        f"{tp['workers_2']['jobs_per_minute']:.1f} (x{tp['speedup_2_workers']:.2f}); queue "
        f"latency p50 {tp['queue_latency_idle_ms']['p50_ms']:.0f} ms p99 "
        f"{tp['queue_latency_idle_ms']['p99_ms']:.0f} ms\n"
        f"wrote {path} in {time.perf_counter() - started:.0f} s"
    )


def bench_loop(
    out: Annotated[Path, typer.Option(help="Output folder; writes loop.json.")],
    qualities: Annotated[str, typer.Option(help="Virtual-subject qualities (comma list).")] = (
        "0.4,0.7,1.0"
    ),
    labels: Annotated[int, typer.Option(min=1, help="Labels per accelerated session.")] = 1000,
    calibration_actions: Annotated[int, typer.Option(min=20)] = 600,
    paced_actions: Annotated[
        int, typer.Option(min=0, help="Actions of the paced session (0: skip it).")
    ] = 1000,
    period_s: Annotated[float, typer.Option(min=0.05, help="Paced seconds per action.")] = 1.5,
    sweep_seeds: Annotated[int, typer.Option(min=1, help="hf-sweep seeds to compare.")] = 3,
    max_passes: Annotated[int | None, typer.Option(min=1, help="Calibration passes.")] = None,
    display: Annotated[
        bool,
        typer.Option(
            help="Watch the paced session on the subject's display page (api + headless "
            "Chromium): measures action -> frame shown."
        ),
    ] = True,
) -> None:
    """Closed loop: accelerated sessions per subject quality, a paced session's timeline."""
    from benchmarks.bench_loop import run_benchmark

    result = run_benchmark(
        out,
        qualities=[float(q) for q in qualities.split(",") if q.strip()],
        labels=labels,
        calibration_actions=calibration_actions,
        paced_actions=paced_actions,
        period_s=period_s,
        sweep_seeds=sweep_seeds,
        max_passes=max_passes,
        display=display,
    )
    typer.echo(f"wrote {out / 'loop.json'} ({len(result['accelerated'])} accelerated sessions)")


def bench_soak(
    out: Annotated[
        Path, typer.Option(help="Folder for soak.json, soak_rss.png and the run's soak-* folder.")
    ],
    minutes: Annotated[float, typer.Option(min=0.5, help="Minutes under load and faults.")] = 5,
    kill_every: Annotated[
        float, typer.Option(min=2, help="Seconds between two SIGKILLs of a random process.")
    ] = 20,
    job_every: Annotated[float, typer.Option(min=1, help="Seconds between two new jobs.")] = 10,
    upload_every: Annotated[
        float, typer.Option(min=1, help="Seconds between two recording uploads.")
    ] = 15,
    live_every: Annotated[
        float,
        typer.Option(min=5, help="Seconds between two live sessions (virtual subject)."),
    ] = 30,
    live_actions: Annotated[
        int, typer.Option(min=2, help="Actions of each live session (accelerated calibration).")
    ] = 30,
    drain: Annotated[
        float, typer.Option(min=0, help="Seconds the jobs get to end after the load.")
    ] = 300,
    job_steps: Annotated[
        int, typer.Option(min=256, help="Env steps of each guided-PPO job.")
    ] = 1024,
    seed: Annotated[int, typer.Option(min=0, help="Seed of which process is killed.")] = 0,
) -> None:
    """Soak with faults: bgrl up under a steady load while random processes are SIGKILLed;
    writes OUT/soak.json (jobs, uploads and live sessions submitted/succeeded/failed/lost,
    orphans, restarts per kind, p99 of reads, RSS growth per hour), OUT/soak_rss.json
    (every process's RSS samples) and OUT/soak_rss.png."""
    from benchmarks.bench_soak import run_soak
    from services.core.files import write_results_json

    output_folder(out)
    report = run_soak(
        out.resolve(),
        minutes=minutes,
        kill_every_s=kill_every,
        job_every_s=job_every,
        upload_every_s=upload_every,
        live_every_s=live_every,
        live_actions=live_actions,
        drain_s=drain,
        seed=seed,
        job_steps=job_steps,
        progress=lambda message: typer.echo(message, err=True),
    )
    write_results_json(out / "soak.json", report)
    jobs, uploads, live = report["jobs"], report["uploads"], report["live_sessions"]
    growth = {kind: rss["growth_per_hour"] for kind, rss in report["rss_mib"].items()}
    typer.echo(
        f"jobs: {jobs['submitted']} submitted, {jobs['succeeded']} succeeded, "
        f"{jobs['failed_with_reason']} failed with a reason, {jobs['lost']} lost; "
        f"uploads: {uploads['submitted']} submitted, {uploads['stored']} stored, "
        f"{uploads['refused_with_reason']} refused, {uploads['lost']} lost; "
        f"live sessions: {live['started']} started, {live['ended_with_data']} ended with "
        f"their data, {live['ended_with_reason']} with the reason, {live['lost']} lost; "
        f"orphans: {report['orphans']}; restarts: {report['restarts']}; "
        f"reads p99 {report['reads']['p99_ms']} ms; RSS growth MiB/h (median per process): "
        f"{growth}; {out / 'soak.json'}"
    )
    if jobs["lost"] or uploads["lost"] or live["lost"] or report["orphans"]:
        raise typer.Exit(1)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl bench sim|eeg|learner|sweep|sb3-peer|api|loop|soak`` and
    ``bgrl eeg quality-sweep``."""
    bench_app.command("sim")(bench_sim)
    bench_app.command("eeg")(bench_eeg)
    bench_app.command("learner")(bench_learner)
    bench_app.command("sweep")(bench_sweep)
    bench_app.command("sb3-peer")(bench_sb3_peer)
    bench_app.command("api")(bench_api)
    bench_app.command("loop")(bench_loop)
    bench_app.command("soak")(bench_soak)
    eeg_app.command("quality-sweep")(quality_sweep_command)
