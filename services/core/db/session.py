"""Engines and session factories for the platform database (SQLite or PostgreSQL)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import pydantic_core
from sqlalchemy import Engine, create_engine, event, exc
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import QueuePool, StaticPool

from services.core.files import PRIVATE_FILE_MODE

SQLITE_BUSY_TIMEOUT_MS = 10_000
PING_AFTER_IDLE_S = 1.0
"""A pooled PostgreSQL connection unused for longer than this is pinged before it is used."""
_IDLE_SINCE = "bgrl_idle_since"


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def _utc_session(dbapi_connection: Any, _record: Any) -> None:
    """Run a new PostgreSQL session in UTC: timestamps then come back in UTC with
    ``datetime.UTC`` as their zone (psycopg's reading of the session's ``TimeZone``), which
    :class:`~services.core.db.base.UtcDateTime` passes through instead of converting each
    one from the server's zone. Committed, so that the pool's rollbacks keep it."""
    with dbapi_connection.cursor() as cursor:
        cursor.execute("SET TIME ZONE 'UTC'")
    dbapi_connection.commit()


def _ping_when_idle(engine: Engine) -> None:
    """Ping a pooled connection at checkout only if it was unused for ``PING_AFTER_IDLE_S``
    (a dead one is replaced: ``DisconnectionError`` makes the pool open another).

    ``pool_pre_ping`` pings at every checkout: one more round trip per request, which at
    hundreds of requests a second costs the api CPU. A connection used less than a second
    ago is not pinged: it can only be dead if the server restarted within that second, and
    then the query fails once and SQLAlchemy recycles the whole pool.
    """

    def used(_dbapi_connection: Any, record: Any, *_: Any) -> None:
        record.info[_IDLE_SINCE] = time.monotonic()

    def checkout(dbapi_connection: Any, record: Any, _proxy: Any) -> None:
        idle_since = record.info.pop(_IDLE_SINCE, None)
        if idle_since is not None and time.monotonic() - idle_since < PING_AFTER_IDLE_S:
            return
        try:
            engine.dialect.do_ping(dbapi_connection)
        except engine.dialect.loaded_dbapi.Error as error:
            raise exc.DisconnectionError(f"connection unusable: {error}") from error

    event.listen(engine, "connect", used)
    event.listen(engine, "checkin", used)
    event.listen(engine, "checkout", checkout)


def _private_sqlite_file(path: Path) -> None:
    """Make the SQLite file (and its folder) readable by its owner only: mode 600 (SQLite
    gives its journal and WAL files the database file's mode).

    An existing file is changed by its path, never opened: closing any descriptor of a
    database file drops the POSIX locks every SQLite connection of this process holds on
    it. A new one is created empty here, before any connection can have opened it.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE))
    except FileExistsError:
        if path.stat().st_mode & 0o777 != PRIVATE_FILE_MODE:
            path.chmod(PRIVATE_FILE_MODE)


def make_engine(url: str, *, connections: int | None = None, **kwargs: Any) -> Engine:
    """An engine for ``url``.

    SQLite: WAL journal (readers never block the writer), foreign keys enforced, a busy
    timeout so concurrent writers (api and workers) wait instead of failing; the folder of
    the file is created. PostgreSQL: a pooled connection idle for a second or more is
    checked before use (:func:`_ping_when_idle`; ``pool_pre_ping=True`` checks every one);
    every session runs in UTC (:func:`_utc_session`).

    ``connections``: a pool of at most this many connections, each opened when first
    needed and then kept (no overflow). SQLAlchemy's default keeps 5 and opens up to 10
    more for a burst, closing each as soon as it is given back: under a steady load above
    5 at a time, a new connection (for PostgreSQL, a server process) for many requests.

    JSON columns are decoded with pydantic-core's parser (the same values as ``json.loads``,
    NaN and Infinity included, in a third of its time: the job list reads two per row).
    """
    parsed = make_url(url)
    kwargs.setdefault("json_deserializer", pydantic_core.from_json)
    if connections is not None and parsed.database != ":memory:":
        kwargs.setdefault("pool_size", connections)
        kwargs.setdefault("max_overflow", 0)
    if parsed.get_backend_name() == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            _private_sqlite_file(Path(parsed.database))
        kwargs.setdefault("connect_args", {"check_same_thread": False})
        engine = create_engine(url, **kwargs)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    ping_every_checkout = kwargs.setdefault("pool_pre_ping", False)
    engine = create_engine(url, **kwargs)
    event.listen(engine, "connect", _utc_session)
    if not ping_every_checkout:
        _ping_when_idle(engine)
    return engine


def pool_capacity(engine: Engine) -> int:
    """How many sessions of ``engine`` can hold a connection at once: size + overflow of a
    ``QueuePool`` (the default for a SQLite file and PostgreSQL), 1 for a ``StaticPool``
    (one shared connection), else 64 (pools that open a connection per thread or use)."""
    pool = engine.pool
    if isinstance(pool, QueuePool):
        return pool.size() + max(pool._max_overflow, 0)
    if isinstance(pool, StaticPool):
        return 1
    return 64


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions bound to ``engine``; objects stay readable after commit."""
    return sessionmaker(bind=engine, expire_on_commit=False)
