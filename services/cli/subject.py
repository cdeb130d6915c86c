"""``bgrl subject simulate``: a virtual subject's calibration recording (synthetic BDF)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, cast

import numpy as np
import typer
from tqdm import tqdm

from services.cli.paths import output_file

subject_app = typer.Typer(help="Virtual subjects: synthetic ErrP EEG recordings.")


def random_policy_labels(
    n_actions: int, *, seed: int, task: Literal["sssg", "vssg"] = "sssg", progress: bool = False
) -> np.ndarray:
    """Oracle labels of a uniformly random policy in the default map.

    Each action is correct iff it is in ``env.optimal_actions()`` of the state it was taken
    in; the env is reset when an episode ends (goal, collision or the 120-step limit).

    Returns
    -------
    labels : ndarray of bool, shape (n_actions,)
        True for a correct action, False for an error.
    """
    from services.sim import MAX_EPISODE_STEPS
    from services.sim.env import BrainNavEnv

    rng = np.random.default_rng(seed)
    labels = np.empty(n_actions, dtype=bool)
    env = BrainNavEnv(task=task)
    try:
        env.reset(seed=seed)
        steps = 0
        for i in tqdm(range(n_actions), desc="random policy", unit="action", disable=not progress):
            action = int(rng.integers(env.action_space.n))
            labels[i] = action in env.optimal_actions()
            _, _, terminated, _, _ = env.step(action)
            steps += 1
            if terminated or steps >= MAX_EPISODE_STEPS:
                env.reset()
                steps = 0
    finally:
        env.close()
    return labels


@subject_app.command("simulate")
def simulate_command(
    out: Annotated[Path, typer.Option(help="Output BDF file.")],
    quality: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="ErrP quality: 0 none, 1 the clearest.")
    ] = 0.6,
    actions: Annotated[int, typer.Option(min=1, help="Number of actions (one per 1.5 s).")] = 600,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the policy and of the subject.")] = 0,
    task: Annotated[str, typer.Option(help="Task the random policy acts in: sssg or vssg.")] = (
        "sssg"
    ),
) -> None:
    """Write a virtual subject's calibration recording (SYNTHETIC) as a 24-bit BDF file."""
    from services.eeg.recordings.io import file_sha256, write_bdf
    from services.eeg.virtual.subject import SyntheticRecording

    if task not in ("sssg", "vssg"):
        raise typer.BadParameter(f"task must be sssg or vssg, got {task!r}", param_hint="--task")
    output_file(out, suffixes=(".bdf",))
    task_name = cast(Literal["sssg", "vssg"], task)
    labels = random_policy_labels(actions, seed=seed, task=task_name, progress=True)
    with tqdm(total=2, desc="EEG", unit="stage") as bar:
        recording = SyntheticRecording(labels.tolist(), quality=quality, seed=seed)
        bar.update()
        path = write_bdf(recording, out)  # generated and written block by block
        bar.update()
    error_fraction = float(np.mean(~labels))
    duration_s = (recording.n_times - 1) / recording.info["sfreq"]
    typer.echo(f"wrote {path} (SYNTHETIC, {duration_s:.0f} s, {actions} actions)")
    typer.echo(f"sha256 {file_sha256(path)}")
    typer.echo(f"error fraction {error_fraction:.3f}")


@subject_app.command("stream")
def stream_command(
    recording: Annotated[
        Path | None,
        typer.Argument(help="Recording to replay (BDF, EDF or FIF); none: the live subject."),
    ] = None,
    name: Annotated[str, typer.Option(help="LSL stream name.")] = "BrainNav-EEG",
    chunk_size: Annotated[int, typer.Option(min=1, help="Samples per LSL chunk.")] = 64,
    repeat: Annotated[int, typer.Option(min=1, help="How many times to play it.")] = 1,
    quality: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Live subject: ErrP quality (0 none, 1 best).")
    ] = 0.6,
    seed: Annotated[int, typer.Option(min=0, help="Live subject: seed of the subject.")] = 0,
    sfreq: Annotated[float, typer.Option(min=256.0, help="Live subject: sampling rate.")] = 256.0,
    marker_stream: Annotated[
        str, typer.Option(help="Live subject: the sim's LSL marker stream to follow.")
    ] = "BrainNav-Markers",
    duration: Annotated[
        float, typer.Option(min=0.0, help="Live subject: stop after this many s (0: Ctrl-C).")
    ] = 0.0,
) -> None:
    """Stream EEG over LSL in real time; Ctrl-C stops.

    With RECORDING, replay it (Status triggers included). Without, stream the virtual
    subject live (SYNTHETIC), its ErrPs driven by the oracle labels of the sim's markers.
    """
    import time

    from services.eeg.live.lsl import replay
    from services.eeg.recordings.io import RecordingError, read_recording

    if recording is None:
        from services.cli.subject_live import stream_virtual_subject

        stream_virtual_subject(
            quality=quality,
            seed=seed,
            sfreq=sfreq,
            name=name,
            marker_stream=marker_stream,
            duration_s=duration,
        )
        return
    try:
        raw = read_recording(recording)
    except RecordingError as exc:
        raise typer.BadParameter(str(exc), param_hint="RECORDING") from exc
    duration = raw.n_times / raw.info["sfreq"] * repeat
    tag = " (SYNTHETIC)" if (raw.info.get("description") or "").startswith("SYNTHETIC") else ""
    player = replay(raw, name=name, chunk_size=chunk_size, n_repeat=repeat)
    typer.echo(f"streaming {recording.name}{tag} as LSL stream {name!r} for {duration:.0f} s")
    try:
        with tqdm(total=round(duration), desc="replay", unit="s") as bar:
            start = time.monotonic()
            while (elapsed := time.monotonic() - start) < duration:
                bar.n = min(round(elapsed), bar.total)
                bar.refresh()
                time.sleep(0.5)
    except KeyboardInterrupt:
        typer.echo("stopped")
    finally:
        player.stop()


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl subject ...`` to the command line."""
    app.add_typer(subject_app, name="subject")
