"""``bgrl bids export``: a subject's sessions as a BIDS dataset, from the platform's database
and artifact store (the same export as the api's ``bids_export`` job, without the queue)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

bids_app = typer.Typer(help="BIDS datasets of the platform's subjects.", no_args_is_help=True)


@bids_app.command("export")
def export(
    subject: Annotated[str, typer.Option(help="The subject's code (as in the platform).")],
    out: Annotated[Path, typer.Option(help="Folder of the dataset (created; must be empty).")],
    zip_file: Annotated[
        Path | None, typer.Option("--zip", help="Also write the dataset as this zip file.")
    ] = None,
) -> None:
    """Write SUBJECT's sessions (recordings, or the virtual subject's regenerated stream) as a
    BIDS dataset in OUT, with the platform's settings (BGRL_DATABASE_URL, BGRL_ARTIFACT_DIR).
    Prints the summary as JSON."""
    from services.core.db.migrate import upgrade_database
    from services.core.queue import make_celery
    from services.core.settings import SettingsError, load_settings
    from services.worker.bids import export_subject, subject_id_for_code, zip_folder
    from services.worker.runtime import JobConfigError, Runtime
    from services.worker.settings import WorkerSettings

    try:
        settings = load_settings(WorkerSettings)
    except SettingsError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    upgrade_database(settings.resolved_database_url)
    runtime = Runtime(settings=settings, celery=make_celery(settings))
    try:
        summary = export_subject(runtime, subject_id_for_code(runtime, subject), out)
    except JobConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    finally:
        runtime.engine.dispose()
    if zip_file is not None:
        zip_folder(out, zip_file)
    typer.echo(json.dumps(summary, indent=2))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bids`` to the ``bgrl`` command."""
    app.add_typer(bids_app, name="bids")
