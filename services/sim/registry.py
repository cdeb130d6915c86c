"""The sessions of one sim service and the maps its clients may name.

:class:`SessionRegistry` bounds the number of open sessions, closes idle ones and
remembers closed ids (410, not 404); :func:`resolve_map` turns a client's map name into a
validated map whose goal the oracle can reach.
"""

from __future__ import annotations

import contextlib
import threading
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from services.sim.errors import (
    MapRequestError,
    SessionClosedError,
    SessionLimitError,
    SessionNotFoundError,
)
from services.sim.lsl_markers import MarkerPublisher
from services.sim.maps import DEFAULT_MAP_PATH, MAPS_DIR, MapError, NavMap, load_map
from services.sim.oracle import Oracle
from services.sim.sessions import RewardMode, SimSession, Task

MAP_SUFFIX = ".json"


def available_maps(extra_dirs: tuple[Path, ...] = ()) -> dict[str, Path]:
    """Map files sessions may load, by name (file stem); shipped maps win name clashes."""
    maps: dict[str, Path] = {}
    for folder in (*extra_dirs, MAPS_DIR):
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if path.suffix.lower() == MAP_SUFFIX and path.is_file():
                maps[path.stem] = path.resolve()
    return maps


def resolve_map(
    spec: str | None, extra_dirs: tuple[Path, ...] = (), oracle_cache_dir: Path | None = None
) -> tuple[str, Path, NavMap]:
    """Turn a client's map name or path into ``(name, path, validated map)``.

    ``spec`` is a map name (file stem, e.g. ``"default"``) or a path to a map file inside the
    shipped maps folder or one of ``extra_dirs``; ``None`` means the default map. The map's
    oracle is built (or loaded from ``oracle_cache_dir``) to check that the goal can be
    reached. Raises :class:`MapRequestError` naming the problem for anything else.
    """
    allowed = available_maps(extra_dirs)
    if spec is None:
        path = DEFAULT_MAP_PATH.resolve()
    elif spec in allowed:
        path = allowed[spec]
    else:
        try:
            candidate = Path(spec).expanduser().resolve()
        except (ValueError, OSError, RuntimeError):  # a NUL byte, no home folder, a loop
            candidate = None
        if candidate not in allowed.values():
            raise MapRequestError(
                f"unknown map {spec!r}: give the name or path of one of the maps this service "
                f"ships or is configured with: {sorted(allowed)}"
            )
        path = candidate
    try:
        nav_map = load_map(path)
        Oracle.for_map(nav_map, oracle_cache_dir).check_reachable(f"map file {path}")
    except MapError as exc:
        raise MapRequestError(f"map {spec or path.stem!r} is invalid: {exc}") from exc
    return path.stem, path, nav_map


@dataclass
class SessionRegistry:
    """All sessions of one service instance, bounded by ``max_sessions``.

    A session unused for ``idle_timeout_s`` (no request, no step, no streamed frame, no
    paced mode) is closed when a new session is opened, so clients that vanish without
    closing their sessions cannot exhaust ``max_sessions``.
    """

    max_sessions: int
    idle_timeout_s: float = 3600.0
    publisher: MarkerPublisher | None = None
    extra_map_dirs: tuple[Path, ...] = ()
    frame_size: tuple[int, int] = (320, 240)
    max_queued_actions: int = 1000
    oracle_cache_dir: Path | None = None
    _sessions: dict[str, SimSession] = field(default_factory=dict)
    _opening: int = 0
    _closed: OrderedDict[str, str] = field(default_factory=OrderedDict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def create(
        self,
        *,
        task: Task = "sssg",
        reward_mode: RewardMode = "sparse",
        map_spec: str | None = None,
        seed: int | None = None,
    ) -> SimSession:
        """Open a session (the env is built and reset with ``seed``)."""
        map_name, map_path, nav_map = resolve_map(
            map_spec, self.extra_map_dirs, self.oracle_cache_dir
        )
        session_id = uuid.uuid4().hex
        self.close_idle()
        with self._lock:
            if len(self._sessions) + self._opening >= self.max_sessions:
                raise SessionLimitError(
                    f"{len(self._sessions) + self._opening} sessions are open, the limit "
                    f"(max_sessions) is {self.max_sessions}; close one first"
                )
            self._opening += 1
        try:
            session = SimSession(
                session_id,
                task=task,
                reward_mode=reward_mode,
                map_name=map_name,
                map_path=map_path,
                nav_map=nav_map,
                seed=seed,
                publisher=self.publisher,
                frame_size=self.frame_size,
                max_queued_actions=self.max_queued_actions,
                oracle_cache_dir=self.oracle_cache_dir,
            )
        except BaseException:
            with self._lock:
                self._opening -= 1
            raise
        with self._lock:
            self._opening -= 1
            self._sessions[session_id] = session
        return session

    def get(self, session_id: str) -> SimSession:
        """The open session with this id; 404/410 errors otherwise."""
        with self._lock:
            session = self._sessions.get(session_id)
            if session is None:
                if session_id in self._closed:
                    raise SessionClosedError(f"session {session_id} {self._closed[session_id]}")
                raise SessionNotFoundError(f"no session with id {session_id!r}")
        session.touch()
        return session

    def list(self) -> list[SimSession]:
        """Open sessions, oldest first."""
        with self._lock:
            return list(self._sessions.values())

    def close(self, session_id: str, *, reason: str = "is closed") -> None:
        """Close a session and remember its id (closed ids answer 410, not 404)."""
        session = self.get(session_id)
        with self._lock:
            self._sessions.pop(session_id, None)
            self._closed[session_id] = reason
            while len(self._closed) > 10_000:
                self._closed.popitem(last=False)
        session.close()

    def close_idle(self) -> list[str]:
        """Close the sessions idle for longer than ``idle_timeout_s``; returns their ids."""
        idle = [s.id for s in self.list() if s.idle_for() > self.idle_timeout_s]
        for session_id in idle:
            reason = f"was closed after more than {self.idle_timeout_s:g} s without use"
            with contextlib.suppress(SessionNotFoundError, SessionClosedError):
                self.close(session_id, reason=reason)
        return idle

    def close_all(self) -> None:
        """Close every session (service shutdown)."""
        for session in self.list():
            self.close(session.id)
