"""``bgrl sim ...`` commands."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from services.cli.paths import output_file

sim_app = typer.Typer(help="The navigation simulator: map images, marker stream, checks.")


def _oracle_cache_dir() -> Path:
    """``$BGRL_DATA_DIR/sim/oracle`` from the sim's settings (a bad setting: one line)."""
    from services.core.settings import SettingsError, load_settings
    from services.sim.settings import SimSettings

    try:
        return load_settings(SimSettings).oracle_cache_dir
    except SettingsError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


@sim_app.command("map-png")
def map_png(
    out: Annotated[Path, typer.Option(help="PNG file to write.")],
    map_path: Annotated[
        Path | None, typer.Option("--map", help="Map JSON file (default: the shipped map).")
    ] = None,
    oracle_path: Annotated[
        bool, typer.Option(help="Draw the oracle policy's path from the start.")
    ] = True,
) -> None:
    """Render a map's top-down image, with the oracle's shortest path from the start."""
    from PIL import Image

    from services.sim.env import BrainNavEnv
    from services.sim.maps import MapError

    output_file(out, suffixes=(".png",))
    try:
        env = BrainNavEnv(map_path=map_path, oracle_cache_dir=_oracle_cache_dir())
    except MapError as exc:
        raise typer.BadParameter(str(exc), param_hint="--map") from None
    try:
        env.reset(seed=0)
        steps = 0
        if oracle_path:
            x, y, yaw = env.pose
            for action in env.oracle.rollout(x, y, yaw) or []:
                env.step(action)
                steps += 1
        image = env.top_down_image()
    finally:
        env.close()
    Image.fromarray(image).save(out)
    detail = f", oracle path {steps} actions" if oracle_path else ""
    typer.echo(f"wrote {out} ({image.shape[1]}x{image.shape[0]} px{detail})")


@sim_app.command("random-success")
def random_success(
    task: Annotated[str, typer.Option(help="sssg or vssg.")] = "vssg",
    episodes: Annotated[int, typer.Option(min=1, help="120-step episodes to run.")] = 10_000,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the actions and starts.")] = 0,
    map_path: Annotated[
        Path | None, typer.Option("--map", help="Map JSON file (default: the shipped map).")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Also write the result as JSON here.")] = None,
) -> None:
    """How often a uniformly random policy reaches the goal (the paper's premise: rarely)."""
    from dataclasses import asdict

    from services.core.files import write_json_atomic
    from services.sim.maps import MapError
    from services.sim.metrics import random_policy_success_rate

    if task not in ("sssg", "vssg"):
        raise typer.BadParameter(f"must be sssg or vssg, got {task!r}", param_hint="--task")
    if out is not None:
        output_file(out)
    try:
        result = random_policy_success_rate(
            task,
            episodes=episodes,
            seed=seed,
            map_path=map_path,
            progress=True,
            oracle_cache_dir=_oracle_cache_dir(),
        )
    except MapError as exc:
        raise typer.BadParameter(str(exc), param_hint="--map") from None
    summary = {**asdict(result), "task": task, "seed": seed, "map": str(map_path or "default")}
    if out is not None:
        write_json_atomic(out, summary, indent=2)
    typer.echo(
        f"{task}: {result.successes}/{result.episodes} random episodes reached the goal "
        f"({100 * result.success_rate:.3f} %), {100 * result.collision_rate:.1f} % collided"
    )


@sim_app.command("markers")
def markers(
    count: Annotated[int, typer.Option(min=1, help="Stop after this many markers.")] = 10,
    timeout: Annotated[
        float, typer.Option(min=0.1, help="Give up after this many seconds without a marker.")
    ] = 30.0,
    source_id: Annotated[
        str | None,
        typer.Option(help="Only the stream with this LSL source_id (BGRL_SIM_MARKER_SOURCE_ID)."),
    ] = None,
) -> None:
    """Print action markers from the sim's LSL marker stream as JSON lines.

    A quick check that EEG recordings will carry them.
    """
    from mne_lsl.lsl import StreamInlet, resolve_streams

    from services.core.markers import MARKER_STREAM_NAME, ActionMarker

    infos = resolve_streams(timeout=timeout, name=MARKER_STREAM_NAME, source_id=source_id)
    if not infos:
        which = f" with source_id {source_id!r}" if source_id else ""
        typer.echo(
            f"no LSL stream named {MARKER_STREAM_NAME!r}{which} found in {timeout} s", err=True
        )
        raise typer.Exit(1)
    inlet = StreamInlet(infos[0])
    inlet.open_stream(timeout=timeout)
    offset = inlet.time_correction(timeout=timeout)
    typer.echo(f"listening to {MARKER_STREAM_NAME} from {infos[0].source_id}", err=True)
    for _ in range(count):
        sample, timestamp = inlet.pull_sample(timeout=timeout)
        if timestamp is None:
            typer.echo(f"no marker within {timeout} s", err=True)
            raise typer.Exit(1)
        marker = ActionMarker.from_lsl(sample[0])
        typer.echo(json.dumps({**marker.model_dump(mode="json"), "local_time": timestamp + offset}))
    inlet.close_stream()


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl sim ...``."""
    app.add_typer(sim_app, name="sim")
