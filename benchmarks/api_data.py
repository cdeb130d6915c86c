"""The database the api benchmarks read: a private PostgreSQL schema (or none) and stored
jobs shaped like a worker's, shared by ``bgrl bench api`` (:mod:`benchmarks.bench_api`) and the
CPU-per-request measure (:mod:`benchmarks.api_cpu`)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta

from sqlalchemy import create_engine, insert, text

from services.core.db.models import Job as JobRow
from services.core.db.session import make_engine

ADMIN_EMAIL = "bench@lab.test"
PG_ADMIN_URLS = (
    "postgresql+psycopg://postgres@127.0.0.1:5432/test",
    "postgresql+psycopg://root@127.0.0.1:5432/test",
)
PG_SKIP_REASON = "no PostgreSQL at 127.0.0.1:5432 (database 'test', user postgres or root)"
THROUGHPUT_CONFIG = {
    "task": "sssg",
    "method": "hf_sparse",
    "accuracy": 0.7,
    "total_steps": 2000,
}
"""The guided_ppo config of the throughput jobs (and of the stored ones, at 40k steps)."""


@contextmanager
def postgres_schema() -> Iterator[str | None]:
    """A private schema of PostgreSQL's ``test`` database (dropped afterwards), or None."""
    for admin_url in PG_ADMIN_URLS:
        try:
            admin = create_engine(
                admin_url, isolation_level="AUTOCOMMIT", connect_args={"connect_timeout": 2}
            )
            with admin.connect() as connection:
                connection.execute(text("SELECT 1"))
            break
        except Exception:
            continue
    else:
        yield None
        return
    schema = f"bgrl_bench_{uuid.uuid4().hex[:12]}"
    with admin.connect() as connection:
        connection.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        yield f"{admin_url}?options=-csearch_path%3D{schema}"
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def store_jobs(database_url: str, count: int) -> None:
    """Insert ``count`` finished guided_ppo jobs shaped like a worker's (config, result,
    curve), created a minute apart; nothing is enqueued."""
    statuses = ("succeeded", "succeeded", "succeeded", "failed", "cancelled")
    start = datetime.now(UTC) - timedelta(minutes=count)
    rows = []
    for i in range(count):
        status = statuses[i % len(statuses)]
        created = start + timedelta(minutes=i)
        curve = [[step, round(0.02 * k, 3)] for k, step in enumerate(range(0, 40_001, 2000))]
        config = {
            **THROUGHPUT_CONFIG,
            "total_steps": 40_000,
            "seed": i,
            "hf_treatment": "authors",
            "n_labels": 1000,
            "ppo": {},
        }
        result = None
        if status == "succeeded":
            result = {
                "task": "sssg",
                "method": "hf_sparse",
                "accuracy": 0.7,
                "seed": i,
                "total_steps": 40_000,
                "final_spl": 0.71,
                "last5_spl": 0.69,
                "sampled_success_rate": 0.9,
                "curve_steps": [p[0] for p in curve],
                "curve_spl": [p[1] for p in curve],
                "wall_time_s": 612.5,
                "weights_sha256": uuid.uuid4().hex * 2,
            }
        rows.append(
            {
                "id": uuid.uuid4().hex,
                "kind": "guided_ppo",
                "config": config,
                "status": status,
                "progress": 1.0 if status == "succeeded" else 0.4,
                "attempts": 1,
                "max_attempts": 3,
                "steps_done": 40_000 if status == "succeeded" else 16_000,
                "curve": curve,
                "result": result,
                "error": "ValueError: example failure" if status == "failed" else None,
                "cancel_requested": status == "cancelled",
                "created_at": created,
                "updated_at": created + timedelta(minutes=10),
                "started_at": created + timedelta(seconds=1),
                "finished_at": created + timedelta(minutes=10),
            }
        )
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            connection.execute(insert(JobRow), rows)
    finally:
        engine.dispose()
