"""Entry point of the ``bgrl`` command (the composition root).

Each service contributes its commands through a ``register(app, bench_app)`` function in
its own module under ``services/cli``; this file only assembles them.
"""

from __future__ import annotations

import typer

from services.cli import serve

app = typer.Typer(
    name="bgrl",
    help="Brain-guided RL platform: simulate, calibrate, learn, reproduce, benchmark.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)
bench_app = typer.Typer(help="Performance benchmarks; each writes JSON.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

for module in (serve,):
    module.register(app, bench_app)


if __name__ == "__main__":
    app()
