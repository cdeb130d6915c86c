"""The Dijkstra oracle (all costs 1, so breadth-first search) and simulated noisy feedback.

The oracle labels actions optimal or not, as the paper's simulated teacher and as the
ground truth for ErrP trials. It searches an (x, y, heading) lattice once per map:

- cells of :data:`CELL_M` (1 cm) over the floor and :data:`N_HEADINGS` (12) headings
  ``start yaw + k * 30 deg``, the only headings the robot can have;
- the lattice is conservative: a cell is free when the footprint disc is clear anywhere in
  the cell, and a goal cell when the whole cell is within the goal radius;
- robust: a forward move from anywhere in a cell lands in one of four cells, and counts
  with the worst of their values; turns change only the heading;
- backward breadth-first search from the goal cells, vectorised over the frontier, gives
  the cost-to-go ``V`` of every lattice state (stored as int16, -1 unreachable). ``V`` is
  achievable from every pose in its cell, so greedy descent never loops; it may exceed the
  exact continuous optimum by a step where the way is tight.

For a continuous pose the oracle evaluates each action exactly as the env does (the same
kinematics, footprint sweep and goal test) and scores it ``1 + V(next)`` (0 in the goal,
infinite on a collision). :meth:`Oracle.optimal_actions` returns every action with the
lowest score; the oracle *policy* breaks ties in favour of forward, then left, then right.
:meth:`Oracle.cost_to_go` is the number of actions the oracle policy takes from a pose to
the goal (at most ``V``), so the policy reaches the goal in exactly that many steps; each
oracle remembers the remaining length of the states on the paths it walked (a bounded memo,
:data:`PATH_MEMO_MAX_STATES`), so queries along a walked path are answered at once.

Built lattices are cached in memory per process (one build per map: concurrent callers
wait for the first) and, when a ``cache_dir`` is given, on disk, keyed by the map's content
hash and the lattice parameters. The services and the CLI pass
``$BGRL_DATA_DIR/sim/oracle`` (:attr:`services.sim.settings.SimSettings.oracle_cache_dir`);
a plain ``gymnasium.make`` writes nothing.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import threading
from pathlib import Path
from typing import ClassVar

import numpy as np

from services.core.actions import FORWARD_STEP_M, N_ACTIONS, TURN_STEP_RAD, Action
from services.sim.maps import FOOTPRINT_RADIUS_M, SWEEP_SAMPLE_M, MapError, NavMap, wrap_angle

CELL_M = 0.01
N_HEADINGS = round(2.0 * math.pi / TURN_STEP_RAD)
LATTICE_VERSION = 2
"""Bumped whenever the lattice construction changes, so stale caches are not reused."""
MAX_ROLLOUT_STEPS = 2000
PATH_MEMO_MAX_STATES = 100_000
"""States whose remaining path length an :class:`Oracle` remembers at most (about 20 MB
of Python objects; emptied when full). Sweeps ask ``cost_to_go`` at every step of the
dense and shaped rewards, mostly along paths walked before."""
_TIE_ORDER = (Action.FORWARD, Action.TURN_LEFT, Action.TURN_RIGHT)

logger = logging.getLogger(__name__)


def lattice_margins() -> tuple[int, int]:
    """``(border margin, move span)`` in cells: how far every free cell is from the grid's
    border at least, and how far a forward move's landing cells reach at most.

    Free cells keep the footprint disc off the walls, so they lie at least
    ``FOOTPRINT_RADIUS_M / CELL_M`` cells (40) from the border; a move reaches
    ``floor(FORWARD_STEP_M / CELL_M) + 1`` cells (31). The search indexes the grid flat,
    which is only right while the margin exceeds the span: then no move from a free cell
    leaves the grid or wraps into another row. :func:`check_lattice_invariants` enforces it.
    """
    margin = math.floor(FOOTPRINT_RADIUS_M / CELL_M)
    span = math.floor(FORWARD_STEP_M / CELL_M + 1e-9) + 1
    return margin, span


def check_lattice_invariants() -> None:
    """Raise :class:`RuntimeError` if the lattice parameters break the search's assumptions."""
    margin, span = lattice_margins()
    if margin <= span:
        raise RuntimeError(
            f"oracle lattice: free cells are only {margin} cells from the border but a move "
            f"spans {span} cells (FOOTPRINT_RADIUS_M={FOOTPRINT_RADIUS_M}, CELL_M={CELL_M}, "
            f"FORWARD_STEP_M={FORWARD_STEP_M}): flat indexing would wrap"
        )
    if abs(N_HEADINGS * TURN_STEP_RAD - 2.0 * math.pi) > 1e-9:
        raise RuntimeError(f"TURN_STEP_RAD={TURN_STEP_RAD} does not divide a full turn")


check_lattice_invariants()


def _heading_steps(start_yaw: float) -> np.ndarray:
    """Forward move per heading in cells (float), shape (N_HEADINGS, 2)."""
    yaws = start_yaw + TURN_STEP_RAD * np.arange(N_HEADINGS)
    return FORWARD_STEP_M / CELL_M * np.stack([np.cos(yaws), np.sin(yaws)], axis=1)


def _shifted(mask: np.ndarray, di: int, dj: int) -> np.ndarray:
    """``out[i, j] = mask[i + di, j + dj]``, False outside the grid."""
    nx, ny = mask.shape
    out = np.zeros_like(mask)
    out[max(0, -di) : nx - max(0, di), max(0, -dj) : ny - max(0, dj)] = mask[
        max(0, di) : nx - max(0, -di), max(0, dj) : ny - max(0, -dj)
    ]
    return out


_CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))


def build_cost_to_go(nav_map: NavMap) -> np.ndarray:
    """Robust breadth-first cost-to-go, shape (N_HEADINGS, nx, ny), int16 (-1 = unreachable).

    Cell ``(i, j)`` covers ``[x_min + i * CELL_M, x_min + (i + 1) * CELL_M)`` (likewise in
    y); heading ``k`` is ``start yaw + k * 30 deg``. A forward move from anywhere in cell
    ``c`` lands in one of the four cells ``c + floor(step) + {0, 1}^2``; the move's value is
    the worst of the four, so ``V`` is achievable from every pose in the cell: the greedy
    policy on ``V`` lowers it by at least one per action and cannot loop.
    """
    check_lattice_invariants()
    b = nav_map.bounds
    nx = math.ceil((b.x_max - b.x_min) / CELL_M)
    ny = math.ceil((b.y_max - b.y_min) / CELL_M)
    n_cells = nx * ny
    xs = b.x_min + (np.arange(nx) + 0.5) * CELL_M
    ys = b.y_min + (np.arange(ny) + 0.5) * CELL_M
    half_diag = CELL_M * math.sqrt(0.5)
    # Conservative: the whole cell is clear of obstacles / inside the goal.
    clearance = nav_map.geometry.clearance_grid(xs[:, None], ys[None, :])
    free = clearance >= FOOTPRINT_RADIUS_M + half_diag
    goal_dist = np.hypot(xs[:, None] - nav_map.goal.x, ys[None, :] - nav_map.goal.y)
    goal = free & (goal_dist < nav_map.goal.radius - half_diag)

    steps = _heading_steps(nav_map.start.yaw)
    n_sweep = max(1, math.ceil(FORWARD_STEP_M / SWEEP_SAMPLE_M - 1e-9))
    forward_ok = np.zeros((N_HEADINGS, nx, ny), dtype=bool)
    for k in range(N_HEADINGS):
        ok = free.copy()
        for s in range(1, n_sweep + 1):
            base = np.floor(steps[k] * s / n_sweep).astype(int)
            for ei, ej in _CORNERS:
                ok &= _shifted(free, int(base[0]) + ei, int(base[1]) + ej)
        forward_ok[k] = ok
    margin, span = lattice_margins()
    border = np.ones_like(free)
    border[margin:-margin, margin:-margin] = False
    reach = np.floor(steps)
    if (free & border).any() or np.maximum(np.abs(reach), np.abs(reach + 1)).max() > span:
        raise RuntimeError(
            f"oracle lattice: a free cell within {margin} cells of the border, or a move "
            f"reaching more than {span} cells: flat indexing would wrap"
        )
    forward_ok_flat = forward_ok.reshape(-1)
    # Cells a forward move may land in, as flat offsets: floor(step) + corner.
    landing_base = np.floor(steps).astype(np.int64)
    base_flat = landing_base[:, 0] * ny + landing_base[:, 1]
    corners_flat = np.array([ei * ny + ej for ei, ej in _CORNERS], dtype=np.int64)
    # Free cells are >= margin cells from the border and moves span <= span < margin
    # (checked above), so flat index arithmetic around free cells never wraps a row.

    cost = np.full(N_HEADINGS * n_cells, -1, dtype=np.int16)
    goal_cells = np.flatnonzero(goal.reshape(-1))
    frontier = (np.arange(N_HEADINGS)[:, None] * n_cells + goal_cells[None, :]).reshape(-1)
    cost[frontier] = 0
    stamp = np.zeros(N_HEADINGS * n_cells, dtype=np.int64)

    def unique(idx: np.ndarray) -> np.ndarray:
        stamp[idx] = np.arange(idx.size)  # O(n) deduplication: keep the last occurrence
        return idx[stamp[idx] == np.arange(idx.size)]

    depth = 0
    while frontier.size:
        depth += 1
        k, c = np.divmod(frontier, n_cells)
        # Turning left from k - 1 or right from k + 1 reaches heading k in the same cell.
        turn_pred = np.concatenate(
            [((k - 1) % N_HEADINGS) * n_cells + c, ((k + 1) % N_HEADINGS) * n_cells + c]
        )
        turn_pred = turn_pred[cost[turn_pred] < 0]
        # Forward moves that may land in a newly settled cell ...
        fwd = (frontier[:, None] - base_flat[k][:, None] - corners_flat[None, :]).reshape(-1)
        fwd = unique(fwd[forward_ok_flat[fwd] & (cost[fwd] < 0)])
        # ... count only once every cell they may land in is settled.
        fk = fwd // n_cells
        landing = cost[fwd[:, None] + base_flat[fk][:, None] + corners_flat[None, :]]
        fwd = fwd[np.all((landing >= 0) & (landing < depth), axis=1)]
        frontier = unique(np.concatenate([turn_pred, fwd]))
        cost[frontier] = depth
    return cost.reshape(N_HEADINGS, nx, ny)


def _load_cached(path: Path) -> np.ndarray | None:
    """The cost array stored at ``path``, or None if absent or unreadable (then rebuilt)."""
    try:
        with np.load(path) as data:
            return data["cost"]
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError) as exc:
        logger.warning("ignoring the unreadable oracle cache %s (%s); rebuilding", path, exc)
        return None


def _save_cached(path: Path, cost: np.ndarray) -> None:
    """Write ``cost`` to ``path`` atomically (a temp file in the same folder, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp.npz")
    os.close(fd)
    try:
        np.savez_compressed(tmp, cost=cost)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; other workers read the cache
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class Oracle:
    """Optimal actions and cost-to-go on one map (see the module docstring).

    Build with :meth:`for_map`, which caches in memory and, given a folder, on disk.
    """

    _memory: ClassVar[dict[str, Oracle]] = {}
    _memory_lock: ClassVar[threading.Lock] = threading.Lock()
    _build_locks: ClassVar[dict[str, threading.Lock]] = {}

    def __init__(self, nav_map: NavMap, cost: np.ndarray) -> None:
        expected = (
            N_HEADINGS,
            math.ceil((nav_map.bounds.x_max - nav_map.bounds.x_min) / CELL_M),
            math.ceil((nav_map.bounds.y_max - nav_map.bounds.y_min) / CELL_M),
        )
        if cost.shape != expected or cost.dtype != np.int16:
            raise ValueError(f"cost array must be int16 {expected}, got {cost.dtype} {cost.shape}")
        self.nav_map = nav_map
        self._geometry = nav_map.geometry
        self.cost = cost
        self._nx, self._ny = expected[1], expected[2]
        self._x_min, self._y_min = nav_map.bounds.x_min, nav_map.bounds.y_min
        self._start_yaw = nav_map.start.yaw
        self._goal = (nav_map.goal.x, nav_map.goal.y)
        self._goal_radius = nav_map.goal.radius
        self._path_memo: dict[tuple[float, float, int], int] = {}
        # a forward move's (dx, dy) per heading, as the env computes it from the yaw
        self._forward_steps = [
            (FORWARD_STEP_M * math.cos(yaw), FORWARD_STEP_M * math.sin(yaw))
            for yaw in (self._yaw(k) for k in range(N_HEADINGS))
        ]

    @staticmethod
    def cache_key(nav_map: NavMap) -> str:
        """The cache key: map content hash plus the lattice parameters."""
        return (
            f"{nav_map.content_hash()[:32]}-v{LATTICE_VERSION}-c{CELL_M:g}-r{FOOTPRINT_RADIUS_M:g}"
        )

    @classmethod
    def for_map(cls, nav_map: NavMap, cache_dir: str | Path | None = None) -> Oracle:
        """The map's oracle, from memory, ``cache_dir`` (if given), or built.

        A build is cached in memory and, with ``cache_dir``, written there as
        ``<cache_key>.npz`` (atomically); without ``cache_dir`` nothing is written. Threads
        asking for the same map at once share one build (the others wait for it).
        """
        key = cls.cache_key(nav_map)
        with cls._memory_lock:
            oracle = cls._memory.get(key)
            if oracle is not None:
                return oracle
            build_lock = cls._build_locks.setdefault(key, threading.Lock())
        with build_lock:
            with cls._memory_lock:
                oracle = cls._memory.get(key)
            if oracle is not None:
                return oracle  # built by the thread we waited for
            path = Path(cache_dir) / f"{key}.npz" if cache_dir is not None else None
            cost = _load_cached(path) if path is not None else None
            if cost is None:
                logger.info("building the oracle lattice of map %r", nav_map.name)
                cost = build_cost_to_go(nav_map)
                if path is not None:
                    _save_cached(path, cost)
            oracle = cls(nav_map, cost)
            with cls._memory_lock:
                cls._memory[key] = oracle
                cls._build_locks.pop(key, None)
        return oracle

    @classmethod
    def clear_memory(cls) -> None:
        """Forget every oracle cached in memory (the disk caches stay)."""
        with cls._memory_lock:
            cls._memory.clear()

    def check_reachable(self, source: str = "map") -> None:
        """Raise :class:`MapError` when the goal cannot be reached from the start pose."""
        start = self.nav_map.start
        if not math.isfinite(self.cost_to_go(start.x, start.y, start.yaw)):
            raise MapError(f"{source}: the goal cannot be reached from the start pose")

    # ------------------------------------------------------------- queries
    def heading_index(self, yaw: float) -> int:
        """The lattice heading nearest to ``yaw``."""
        return round(wrap_angle(yaw - self._start_yaw) / TURN_STEP_RAD) % N_HEADINGS

    def _yaw(self, k: int) -> float:
        return wrap_angle(self._start_yaw + k * TURN_STEP_RAD)

    def _in_goal(self, x: float, y: float) -> bool:
        return math.hypot(x - self._goal[0], y - self._goal[1]) < self._goal_radius

    def _lattice_cost(self, x: float, y: float, k: int) -> float:
        fi = (x - self._x_min) / CELL_M
        fj = (y - self._y_min) / CELL_M
        if not (0.0 <= fi < self._nx and 0.0 <= fj < self._ny):  # also NaN and huge values
            return math.inf
        v = self.cost.item(k, math.floor(fi), math.floor(fj))
        return math.inf if v < 0 else float(v)

    def _action_scores(self, x: float, y: float, k: int) -> list[float]:
        """``1 + V(next)`` per action, with the env's own kinematics and collision test."""
        scores = [math.inf] * N_ACTIONS
        dx, dy = self._forward_steps[k]
        nx, ny = x + dx, y + dy
        if not self._geometry.move_collides(x, y, nx, ny):
            scores[Action.FORWARD] = (
                1.0 if self._in_goal(nx, ny) else 1.0 + self._lattice_cost(nx, ny, k)
            )
        here_in_goal = self._in_goal(x, y)  # a turn stays here
        for a, nk in (
            (Action.TURN_LEFT, (k + 1) % N_HEADINGS),
            (Action.TURN_RIGHT, (k - 1) % N_HEADINGS),
        ):
            scores[a] = 1.0 if here_in_goal else 1.0 + self._lattice_cost(x, y, nk)
        return scores

    def optimal_actions(self, x: float, y: float, yaw: float) -> frozenset[int]:
        """Every action with the lowest cost-to-go from this pose (empty if none reaches)."""
        if not _finite(x, y, yaw):
            return frozenset()
        scores = self._action_scores(x, y, self.heading_index(yaw))
        best = min(scores)
        if not math.isfinite(best):
            return frozenset()
        return frozenset(a for a, s in enumerate(scores) if s == best)

    def policy_action(self, x: float, y: float, yaw: float) -> int | None:
        """The oracle policy's action: optimal, ties favour forward, then left, then right."""
        if not _finite(x, y, yaw):
            return None
        scores = self._action_scores(x, y, self.heading_index(yaw))
        best = min(scores)
        if not math.isfinite(best):
            return None
        return next(int(a) for a in _TIE_ORDER if scores[a] == best)

    def _policy_step(self, x: float, y: float, k: int) -> tuple[int, float, float, int] | None:
        """The oracle policy's action from a lattice state and the state it leads to (None
        if no action reaches the goal)."""
        scores = self._action_scores(x, y, k)
        best = min(scores)
        if not math.isfinite(best):
            return None
        a = next(int(a) for a in _TIE_ORDER if scores[a] == best)
        if a == Action.FORWARD:
            dx, dy = self._forward_steps[k]
            return a, x + dx, y + dy, k
        return a, x, y, (k + (1 if a == Action.TURN_LEFT else -1)) % N_HEADINGS

    def rollout(self, x: float, y: float, yaw: float) -> list[int] | None:
        """The oracle policy's actions from a pose to the goal (None if it cannot get there)."""
        if not _finite(x, y, yaw) or self._geometry.collides(x, y):
            return None
        k = self.heading_index(yaw)
        actions: list[int] = []
        seen: set[tuple[float, float, int]] = set()
        while not self._in_goal(x, y):
            state = (x, y, k)
            if state in seen or len(actions) >= MAX_ROLLOUT_STEPS:
                return None
            seen.add(state)
            step = self._policy_step(x, y, k)
            if step is None:
                return None
            a, x, y, k = step
            actions.append(a)
        return actions

    def cost_to_go(self, x: float, y: float, yaw: float) -> float:
        """Actions the oracle policy needs from this pose to the goal (``math.inf`` if none).

        The number :meth:`rollout` would give, walked with the memo of walked paths: the
        walk stops at the first state whose remaining length is remembered, and every state
        of a path that reaches the goal remembers its remaining length (a state's path is
        the suffix of any path through it, the policy being deterministic in the exact
        state). Only successes are remembered; the memo holds at most
        :data:`PATH_MEMO_MAX_STATES` states and is emptied when a path would overflow it.
        """
        if not _finite(x, y, yaw) or self._geometry.collides(x, y):
            return math.inf
        k = self.heading_index(yaw)
        memo = self._path_memo
        walked: list[tuple[float, float, int]] = []
        seen: set[tuple[float, float, int]] = set()
        remaining = 0
        while not self._in_goal(x, y):
            state = (x, y, k)
            known = memo.get(state)
            if known is not None:
                remaining = known
                break
            if state in seen or len(walked) >= MAX_ROLLOUT_STEPS:
                return math.inf
            seen.add(state)
            walked.append(state)
            step = self._policy_step(x, y, k)
            if step is None:
                return math.inf
            _, x, y, k = step
        total = len(walked) + remaining
        if total > MAX_ROLLOUT_STEPS:  # rollout() stops at MAX_ROLLOUT_STEPS actions
            return math.inf
        if len(memo) + len(walked) > PATH_MEMO_MAX_STATES:
            memo.clear()
        for i, state in enumerate(walked):
            memo[state] = total - i
        return float(total)


class NoisyOracleFeedback:
    """Simulated human feedback: the oracle's verdict, flipped at random.

    Parameters
    ----------
    accuracy
        Probability C that the feedback is right, for good and bad actions alike.
    good_accuracy, bad_accuracy
        Separate probabilities of judging an optimal action good and a sub-optimal action
        bad (as in the authors' code); each defaults to ``accuracy``.
    seed
        Seed of the feedback's own random generator.

    Examples
    --------
    >>> fb = NoisyOracleFeedback(0.7, seed=0)
    >>> isinstance(fb.feedback(correct=True), bool)
    True
    """

    def __init__(
        self,
        accuracy: float | None = None,
        *,
        good_accuracy: float | None = None,
        bad_accuracy: float | None = None,
        seed: int | None = None,
    ) -> None:
        good = accuracy if good_accuracy is None else good_accuracy
        bad = accuracy if bad_accuracy is None else bad_accuracy
        if good is None or bad is None:
            raise ValueError("give accuracy, or both good_accuracy and bad_accuracy")
        for name, value in (("good_accuracy", good), ("bad_accuracy", bad)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be within [0, 1], got {value}")
        self.good_accuracy = float(good)
        self.bad_accuracy = float(bad)
        self._rng = np.random.default_rng(seed)

    def feedback(self, correct: bool) -> bool:
        """Feedback on one action the oracle judged ``correct``; True means "good"."""
        accuracy = self.good_accuracy if correct else self.bad_accuracy
        right = bool(self._rng.random() < accuracy)
        return correct if right else not correct
