"""``bgrl worker``: one Celery worker that runs the platform's jobs (what compose runs too)."""

from __future__ import annotations

import logging
import os
import sys
from typing import Annotated

import typer


def worker(
    name: Annotated[
        str | None, typer.Option(help="Worker name in leases and logs (BGRL_WORKER_NAME).")
    ] = None,
    migrate: Annotated[
        bool, typer.Option(help="Bring the database to the current schema before starting.")
    ] = True,
) -> None:
    """Start one job worker with the platform's settings (BGRL_DATABASE_URL, BGRL_BROKER_URL,
    BGRL_ARTIFACT_DIR...); it runs one job at a time. Start several for more."""
    from kombu.utils.url import maybe_sanitize_url

    from services.core.logging import configure_log_file, configure_logging
    from services.core.queue import JOB_QUEUE, broker_url
    from services.core.settings import SettingsError, load_settings
    from services.worker.settings import WorkerSettings

    try:
        settings = load_settings(
            WorkerSettings, **({"worker_name": name} if name is not None else {})
        )
    except SettingsError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    configure_logging(settings.log_level, json_lines=settings.log_json)
    configure_log_file(settings, "worker")
    if migrate:
        from services.core.db.migrate import upgrade_database

        upgrade_database(settings.resolved_database_url)
    from services.platform.jobs import GUIDED_PPO
    from services.worker import app as worker_app

    celery = worker_app.main_app(settings)
    worker_app.load_handler(GUIDED_PPO.name)  # import the learner now, not in the first job
    typer.echo(
        f"worker {settings.owner_name}: broker {maybe_sanitize_url(broker_url(settings))}, "
        f"artifacts {settings.resolved_artifact_dir}",
        err=True,
    )
    code: int | str | None = 0
    try:
        celery.worker_main(
            [
                "worker",
                f"--hostname={settings.owner_name}@%h",
                f"--loglevel={settings.log_level}",
                f"--queues={JOB_QUEUE}",
                "--pool=solo",
                "--concurrency=1",
                "--without-gossip",
                "--without-mingle",
            ]
        )
    except SystemExit as exc:
        code = exc.code
    # Leave at once: finalising the interpreter (torch, pybullet) takes seconds on a busy
    # machine, and `bgrl up` must stop everything within 10 s.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 1)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``worker`` to the ``bgrl`` command."""
    app.command("worker")(worker)
