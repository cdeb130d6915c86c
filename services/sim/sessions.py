"""Sim sessions: one env per session, thread-safe stepping, the paced mode.

The registry of a service's sessions and the map names clients may use are in
:mod:`services.sim.registry`.

Threading model. Each session owns one env and therefore one pybullet DIRECT client.
HTTP handlers, the paced-mode thread and the frame streamer all reach the env only through
:class:`SimSession` methods that hold the session's lock, so the client is never used from
two threads at once. A frame render (~tens of ms) briefly delays a concurrent step, never
the other way round for longer than one step. Listeners (:meth:`SimSession.add_listener`)
are called after the lock is released, from manual steps and the paced mode alike;
``_notify`` refuses to run under the lock, so a listener can never stall other threads.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal

import gymnasium
import numpy as np

from services.core.actions import Action
from services.core.markers import ActionMarker
from services.sim.errors import (
    EpisodeOverError,
    PacedModeError,
    SessionClosedError,
)
from services.sim.lsl_markers import MarkerPublisher, lsl_clock
from services.sim.maps import NavMap
from services.sim.oracle import Oracle

Task = Literal["sssg", "vssg"]
RewardMode = Literal["sparse", "rich", "dense"]
FrameView = Literal["camera", "topdown"]

logger = logging.getLogger(__name__)

ENV_IDS: dict[str, str] = {
    "sssg": "services.sim:BrainNav-SSSG-v0",
    "vssg": "services.sim:BrainNav-VSSG-v0",
}
MARKER_HISTORY = 10_000
"""Markers each session keeps for ``GET /sessions/{id}/markers``."""


# --------------------------------------------------------------------------- json helpers


def to_jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and tuples to JSON types; non-finite floats become None."""
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, (list, tuple, set, frozenset)):
        items = sorted(value) if isinstance(value, (set, frozenset)) else value
        return [to_jsonable(v) for v in items]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


# --------------------------------------------------------------------------- sessions


@dataclass(frozen=True)
class StepOutcome:
    """What one executed action produced."""

    observation: list[float]
    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any]
    marker: ActionMarker


@dataclass(frozen=True)
class OracleAnswer:
    """The oracle's view of one pose."""

    pose: tuple[float, float, float]
    optimal_actions: list[int]
    cost_to_go: float | None
    """Actions to the goal; None when the goal cannot be reached from the pose."""


class PacedPolicy(StrEnum):
    """Who chooses the actions of the paced mode."""

    RANDOM = "random"
    """Uniformly random actions (the ErrP calibration protocol)."""
    ORACLE = "oracle"
    """The oracle policy's action (optimal; ties favour forward, then left, then right)."""
    QUEUE = "queue"
    """Actions queued by the client, one per period; idle while the queue is empty."""


@dataclass
class PacedStatus:
    """State of a session's paced mode."""

    running: bool = False
    policy: PacedPolicy | None = None
    period_s: float | None = None
    auto_reset: bool = True
    max_actions: int | None = None
    actions_executed: int = 0
    queued_actions: int = 0
    error: str | None = None


class SimSession:
    """One env plus everything the service tracks about it.

    Parameters
    ----------
    session_id
        Public id of the session.
    task, reward_mode
        Passed to the env (see :class:`services.sim.env.BrainNavEnv`).
    map_name, map_path, nav_map
        The validated map (see :func:`resolve_map`).
    seed
        Seed of the first reset and of the paced mode's random policy; None draws one.
    publisher
        Where action markers go; None publishes nothing.
    frame_size
        ``(width, height)`` of the camera frames the env renders.
    max_queued_actions
        Bound on the paced-mode action queue.
    oracle_cache_dir
        Disk cache of the oracle lattices (None: memory only).
    """

    def __init__(
        self,
        session_id: str,
        *,
        task: Task,
        reward_mode: RewardMode,
        map_name: str,
        map_path: Path,
        nav_map: NavMap,
        seed: int | None,
        publisher: MarkerPublisher | None,
        frame_size: tuple[int, int] = (320, 240),
        max_queued_actions: int = 1000,
        oracle_cache_dir: Path | None = None,
    ) -> None:
        self.id = session_id
        self.task = task
        self.reward_mode = reward_mode
        self.map_name = map_name
        self.map_path = map_path
        self.nav_map = nav_map
        self.seed = seed
        self.created_at = time.time()
        self.last_active = time.monotonic()
        self._publisher = publisher
        self._lock = threading.RLock()
        self._env = gymnasium.make(
            ENV_IDS[task],
            reward_mode=reward_mode,
            map_path=str(map_path),
            render_mode="rgb_array",
            render_width=frame_size[0],
            render_height=frame_size[1],
            oracle_cache_dir=oracle_cache_dir,
            disable_env_checker=True,
        )
        self._policy_rng = np.random.default_rng(seed)
        self.closed = False
        self.episode = -1
        self.step_count = 0
        self.episode_step = 0
        self.observation: list[float] = []
        self.info: dict[str, Any] = {}
        self.reward: float | None = None
        self.terminated = False
        self.truncated = False
        self.last_marker: ActionMarker | None = None
        self._markers: deque[ActionMarker] = deque(maxlen=MARKER_HISTORY)
        self._state_version = 0
        self._frames: dict[str, tuple[int, np.ndarray]] = {}
        self._paced = PacedStatus()
        self._paced_stop = threading.Event()
        self._paced_thread: threading.Thread | None = None
        self._queue: deque[Action] = deque()
        self._max_queued_actions = max_queued_actions
        self._listeners: set[Callable[[], None]] = set()
        try:
            self.reset(seed)
        except BaseException:
            self._env.close()
            raise

    # ---------------------------------------------------------------- core actions

    @property
    def episode_over(self) -> bool:
        """True once the current episode terminated or was truncated."""
        return self.terminated or self.truncated

    def _check_open(self) -> None:
        if self.closed:
            raise SessionClosedError(f"session {self.id} is closed")

    def touch(self) -> None:
        """Mark the session as in use now (requests, steps and streamed frames do this)."""
        self.last_active = time.monotonic()

    def idle_for(self) -> float:
        """Seconds since the session was last used; 0 while the paced mode runs."""
        with self._lock:
            return 0.0 if self._paced.running else time.monotonic() - self.last_active

    def reset(self, seed: int | None = None) -> tuple[list[float], dict[str, Any]]:
        """Start a new episode; returns the observation and the reset info.

        :class:`PacedModeError` while the paced mode drives the session (checked in the same
        lock hold as the reset, so a paced mode starting meanwhile cannot be overtaken)."""
        with self._lock:
            self._refuse_if_paced()
            observation, info = self._reset_locked(seed)
        self._notify()
        return observation, info

    def step(self, action: int | Action) -> StepOutcome:
        """Execute one action, judge it with the oracle and publish its marker.

        :class:`PacedModeError` while the paced mode drives the session (checked in the same
        lock hold as the step)."""
        with self._lock:
            self._refuse_if_paced()
            outcome = self._step_locked(Action(action))
        self._notify()
        return outcome

    def _reset_locked(self, seed: int | None) -> tuple[list[float], dict[str, Any]]:
        """:meth:`reset` without the listeners; the caller holds the lock and notifies."""
        self._check_open()
        self.touch()
        obs, info = self._env.reset(seed=seed)
        self._state_version += 1
        self.episode += 1
        self.episode_step = 0
        self.observation = to_jsonable(obs)
        self.info = to_jsonable(info)
        self.reward = None
        self.terminated = self.truncated = False
        return self.observation, self.info

    def _step_locked(self, action: Action) -> StepOutcome:
        """:meth:`step` without the listeners; the caller holds the lock and notifies."""
        self._check_open()
        if self.episode_over:
            how = "terminated" if self.terminated else "was truncated"
            raise EpisodeOverError(
                f"episode {self.episode} of session {self.id} {how}; "
                "reset the session to start a new episode"
            )
        self.touch()
        correct = int(action) in self._core.optimal_actions()
        obs, reward, terminated, truncated, info = self._env.step(int(action))
        timestamp = lsl_clock()
        self._state_version += 1
        marker = ActionMarker(
            session_id=self.id,
            step=self.step_count,
            episode=self.episode,
            action=action,
            correct=correct,
            timestamp=timestamp,
        )
        self.step_count += 1
        self.episode_step += 1
        self.observation = to_jsonable(obs)
        self.info = to_jsonable(info)
        self.reward = float(reward)
        self.terminated, self.truncated = bool(terminated), bool(truncated)
        self.last_marker = marker
        self._markers.append(marker)
        if self._publisher is not None:  # under the lock: markers leave in step order
            self._publisher.publish(marker)
        return StepOutcome(
            observation=self.observation,
            reward=self.reward,
            terminated=self.terminated,
            truncated=self.truncated,
            info=self.info,
            marker=marker,
        )

    def markers(self, since_step: int = 0, limit: int = 1000) -> list[ActionMarker]:
        """Markers of this session with ``step >= since_step``, oldest first (the last
        :data:`MARKER_HISTORY` are kept)."""
        with self._lock:
            found = [m for m in self._markers if m.step >= since_step]
        return found[:limit]

    def add_listener(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` (from the stepping thread) after every step and reset.

        The frame stream uses this to send a frame as soon as an action is executed.
        Callbacks run after the session's lock is released (``_notify`` checks it), so a
        slow callback never blocks other threads' steps, renders or reads; they must still
        be quick because they delay the caller of ``step``.
        """
        with self._lock:
            self._listeners.add(callback)

    def remove_listener(self, callback: Callable[[], None]) -> None:
        """Stop calling ``callback``."""
        with self._lock:
            self._listeners.discard(callback)

    def _notify(self) -> None:
        if self._lock._is_owned():  # type: ignore[attr-defined]  # RLock: held by this thread
            raise RuntimeError("session listeners must be called outside the session's lock")
        with self._lock:
            listeners = list(self._listeners)
        for callback in listeners:
            try:
                callback()
            except Exception:  # a broken listener must not break stepping
                logger.exception("listener of session %s failed", self.id)

    def oracle_query(self, pose: tuple[float, float, float] | None = None) -> OracleAnswer:
        """Optimal actions and cost-to-go at ``pose`` (default: the robot's current pose)."""
        with self._lock:
            self._check_open()
            oracle = self._get_oracle()
            x, y, yaw = pose if pose is not None else self._pose()
            cost = float(oracle.cost_to_go(x, y, yaw))
            optimal = sorted(int(a) for a in oracle.optimal_actions(x, y, yaw))
        return OracleAnswer(
            pose=(x, y, yaw),
            optimal_actions=optimal,
            cost_to_go=cost if math.isfinite(cost) else None,
        )

    def render_frame(self, view: FrameView) -> np.ndarray:
        """RGB frame (H, W, 3) uint8 of the current state (read-only).

        ``camera``: the env's third-person frame at the session's frame size; ``topdown``:
        the map with obstacles, goal, robot and the current episode's trajectory. A frame is
        rendered once per state and view: streams of an idle session cost no rendering.
        """
        with self._lock:
            self._check_open()
            cached = self._frames.get(view)
            if cached is not None and cached[0] == self._state_version:
                return cached[1]
            image = self._core.top_down_image() if view == "topdown" else self._env.render()
            image = np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3])
            image.flags.writeable = False
            self._frames[view] = (self._state_version, image)
            return image

    def render_with_state(self, view: FrameView) -> tuple[dict[str, Any], np.ndarray]:
        """:meth:`snapshot` and :meth:`render_frame` of the same instant (one lock hold)."""
        with self._lock:
            self.touch()
            return self.snapshot(), self.render_frame(view)

    def snapshot(self) -> dict[str, Any]:
        """A consistent copy of the session's public state."""
        with self._lock:
            return {
                "id": self.id,
                "task": self.task,
                "reward_mode": self.reward_mode,
                "map": self.map_name,
                "seed": self.seed,
                "created_at": self.created_at,
                "closed": self.closed,
                "episode": self.episode,
                "step": self.step_count,
                "episode_step": self.episode_step,
                "pose": self._pose(),
                "observation": list(self.observation),
                "reward": self.reward,
                "terminated": self.terminated,
                "truncated": self.truncated,
                "info": dict(self.info),
                "last_marker": self.last_marker,
                "paced": self.paced_status(),
            }

    def close(self) -> None:
        """Stop the paced mode and release the env; later calls raise 410 errors."""
        self.stop_paced(missing_ok=True)
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._env.close()

    # ---------------------------------------------------------------- paced mode

    def paced_status(self) -> PacedStatus:
        """A copy of the paced mode's state."""
        with self._lock:
            status = PacedStatus(**vars(self._paced))
            status.queued_actions = len(self._queue)
            return status

    def enqueue(self, actions: list[Action]) -> int:
        """Queue actions for the paced ``queue`` policy; returns the queue length."""
        with self._lock:
            self._check_open()
            if len(self._queue) + len(actions) > self._max_queued_actions:
                raise PacedModeError(
                    f"queue would hold {len(self._queue) + len(actions)} actions; "
                    f"the limit is {self._max_queued_actions}",
                    field="actions",
                )
            self._queue.extend(actions)
            return len(self._queue)

    def clear_queue(self) -> None:
        """Drop every queued action."""
        with self._lock:
            self._queue.clear()

    def start_paced(
        self,
        policy: PacedPolicy,
        *,
        period_s: float,
        auto_reset: bool = True,
        max_actions: int | None = None,
    ) -> PacedStatus:
        """Execute one action every ``period_s`` seconds in a background thread.

        At the first tick after an episode ends the session resets (``auto_reset``) so that
        observers see the final state for one period; otherwise the paced mode stops there.
        It also stops after ``max_actions`` actions or on :meth:`stop_paced`.
        """
        with self._lock:
            self._check_open()
            if self._paced.running:
                raise PacedModeError(f"session {self.id} is already in paced mode")
            self._paced = PacedStatus(
                running=True,
                policy=policy,
                period_s=period_s,
                auto_reset=auto_reset,
                max_actions=max_actions,
            )
            self._paced_stop = threading.Event()
            self._paced_thread = threading.Thread(
                target=self._paced_loop,
                args=(self._paced_stop, self._choose_action(policy)),
                name=f"paced-{self.id}",
                daemon=True,
            )
            self._paced_thread.start()
            return self.paced_status()

    def stop_paced(self, *, missing_ok: bool = False) -> PacedStatus:
        """Stop the paced mode and wait for its thread to finish."""
        with self._lock:
            thread = self._paced_thread
            if thread is None and not missing_ok:
                self._check_open()
                raise PacedModeError(f"session {self.id} is not in paced mode")
            self._paced_stop.set()
            self._paced_thread = None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10.0)
        with self._lock:
            self._paced.running = False
        return self.paced_status()

    def _refuse_if_paced(self) -> None:
        """:class:`PacedModeError` while the paced mode drives the session (lock held)."""
        if self._paced.running:
            raise PacedModeError(
                f"session {self.id} is in paced mode; stop it before stepping or resetting"
            )

    def _choose_action(self, policy: PacedPolicy) -> Callable[[], Action | None]:
        if policy is PacedPolicy.RANDOM:
            return lambda: Action(int(self._policy_rng.integers(len(Action))))
        if policy is PacedPolicy.ORACLE:

            def oracle_action() -> Action:
                action = self._get_oracle().policy_action(*self._pose())
                if action is None:  # no path from here: keep the show going at random
                    return Action(int(self._policy_rng.integers(len(Action))))
                return Action(action)

            return oracle_action

        def queued_action() -> Action | None:
            return self._queue.popleft() if self._queue else None

        return queued_action

    def _paced_loop(self, stop: threading.Event, choose: Callable[[], Action | None]) -> None:
        period = self._paced.period_s or 0.0
        next_tick = time.monotonic()
        try:
            while not stop.wait(max(0.0, next_tick - time.monotonic())):
                next_tick += period
                if next_tick < time.monotonic():  # fell behind: skip missed ticks, keep phase
                    next_tick += period * math.ceil((time.monotonic() - next_tick) / period)
                # Decide and act in one lock hold (a stop or close cannot slip in between);
                # listeners are told after the lock is released.
                with self._lock:
                    if stop.is_set() or self.closed:
                        break
                    if self.episode_over:
                        if not self._paced.auto_reset:
                            break
                        self._reset_locked(None)
                        finished = False
                    else:
                        action = choose()
                        if action is None:
                            continue
                        self._step_locked(action)
                        self._paced.actions_executed += 1
                        limit = self._paced.max_actions
                        finished = limit is not None and self._paced.actions_executed >= limit
                self._notify()
                if finished:
                    break
        except Exception as exc:  # surfaced through the paced status, never swallowed silently
            logger.exception("paced mode of session %s failed", self.id)
            with self._lock:
                self._paced.error = f"{type(exc).__name__}: {exc}"
        finally:
            with self._lock:
                self._paced.running = False

    # ---------------------------------------------------------------- internals

    def _get_oracle(self) -> Oracle:
        return self._core.oracle

    @property
    def _core(self) -> Any:
        return self._env.unwrapped

    def _pose(self) -> tuple[float, float, float]:
        x, y, yaw = self._core.pose
        return float(x), float(y), float(yaw)
