"""Entry point of the ``bgrl`` command (the composition root).

Each service contributes its commands through a ``register(app, bench_app)`` function in
its own module under ``services/cli``, and the benchmarks (a layer above the CLI) theirs
through :func:`benchmarks.commands.register`; this file only assembles them (the one import
of ``benchmarks`` from ``services``, allowed by name in pyproject's import contract).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Annotated

import typer

from benchmarks import commands as benchmark_commands
from services.cli import (
    backup,
    bids,
    demo,
    eeg,
    learner,
    platform,
    serve,
    sim,
    subject,
    users,
    worker,
)

app = typer.Typer(
    name="bgrl",
    help="Brain-guided RL platform: simulate, calibrate, learn, reproduce, benchmark.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)
bench_app = typer.Typer(help="Performance benchmarks; each writes JSON.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

for module in (serve, worker, learner, sim, eeg, subject, platform, users, demo, bids, backup):
    module.register(app, bench_app)
benchmark_commands.register(app, bench_app)


@bench_app.command("all")
def bench_all(
    out: Annotated[Path, typer.Option(help="Folder for the JSON results.")] = Path(
        "benchmarks/results"
    ),
) -> None:
    """Run every benchmark, each in its own process, writing OUT/<name>.json."""
    names = [c.name for c in bench_app.registered_commands if c.name and c.name != "all"]
    failed = []
    for name in names:
        typer.echo(f"== bench {name}")
        cmd = [sys.executable, "-m", "services.cli.main", "bench", name, "--out", str(out)]
        if subprocess.run(cmd, check=False).returncode != 0:
            failed.append(name)
    if failed:
        typer.echo(f"failed: {', '.join(failed)}", err=True)
        raise typer.Exit(1)


if __name__ == "__main__":
    app()
