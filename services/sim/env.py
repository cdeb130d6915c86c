"""The brain-guided navigation task as a Gymnasium env on pybullet (Akinola et al., 2020)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ClosedEnvironmentError

from services.core.actions import FORWARD_STEP_M, N_ACTIONS, TURN_STEP_RAD, Action
from services.sim import bullet, rendering
from services.sim.bullet import pybullet
from services.sim.maps import (
    DEFAULT_MAP_PATH,
    FOOTPRINT_RADIUS_M,
    NavMap,
    load_map,
    wrap_angle,
)
from services.sim.oracle import Oracle
from services.sim.world import (
    RayMemo,
    acquire_shared_world,
    build_world,
    release_shared_world,
)

N_RAYS = 10
RAY_LENGTH_M = 13.0
RAY_ANGLES_RAD = np.linspace(-math.pi / 2.0, math.pi / 2.0, N_RAYS)
"""Ray directions relative to the robot's heading, evenly over -90..+90 degrees."""
OBS_SIZE = N_RAYS + 3

GOAL_REWARD = 100.0
COLLISION_REWARD = -100.0
STEP_REWARD = -1.0
RICH_DISTANCE_COEF = -1.0
RICH_HEADING_COEF = -0.3
SHAPING_GAMMA = 0.99
"""Default discount of the shaping term: the learner's gamma (PPOConfig.gamma)."""
DENSE_DISTANCE_COEF = 0.3
"""The dense reward's cost per step and per action of the oracle's path from the new pose
(alpha). 0.3 since 2026-12-05 (0.1 before): chosen among 0.03 / 0.1 / 0.3 / 0.6 / 1.0 on
our PPO's tuning seeds 0-9 (VSSG) and checked on fresh seeds (docs/reproduction.md, "The
dense reward's alpha")."""
NO_PATH_STEPS = 120.0
"""Cost-to-go given to a pose from which the oracle finds no way to the goal (about 0.7 %
of a random walk's poses, pressed against a wall): the episode's time limit."""

Task = Literal["sssg", "vssg"]
RewardMode = Literal["sparse", "rich", "shaped", "dense"]
REWARD_MODES: tuple[RewardMode, ...] = ("sparse", "rich", "shaped", "dense")

MAX_RENDER_SIZE = 4096
"""Largest ``render_width`` / ``render_height`` (px): TinyRenderer allocates the whole frame."""

_TWO_PI = 2.0 * math.pi
_N_HEADINGS = round(_TWO_PI / TURN_STEP_RAD)


class BrainNavEnv(gym.Env[np.ndarray, np.int64]):
    """Husky navigation to a fixed goal on an 11 x 12 m floor with obstacles.

    ## Description

    The navigation task of Akinola et al., "Accelerated Robot Learning via Human Brain
    Signals" (ICRA 2020): a Husky robot moves on a floor with walls and box obstacles and
    must reach a blue goal pillar without colliding. The robot is moved kinematically (no
    dynamics); pybullet (DIRECT, one client per env) provides the range sensor and frames.
    ``task="sssg"`` always starts at the map's start pose (Same Start Same Goal);
    ``task="vssg"`` draws the start uniformly from a square of side ``start_jitter``
    (0.2 m on the default map) around it (Variable Start Same Goal).

    ## Action Space

    ``Discrete(3)``: 0 move forward 0.3 m, 1 turn 30 degrees left (counter-clockwise),
    2 turn 30 degrees right (see :class:`services.core.actions.Action`).

    ## Observation Space

    ``Box(13,)`` float32, SI units, not normalised:

    | Index | Observation                                             | Min  | Max      |
    |-------|---------------------------------------------------------|------|----------|
    | 0-9   | ray distance (m), -90..+90 deg from the heading, evenly | 0    | 13       |
    | 10    | distance to the goal (m)                                | 0    | diagonal |
    | 11    | bearing to the goal, world frame (rad)                  | -pi  | pi       |
    | 12    | yaw (rad)                                               | -pi  | pi       |

    Rays start at the robot's centre, 0.4 m above the floor, and ignore the robot's body.

    ## Rewards

    ``reward_mode="sparse"``: +100 on reaching the goal, -100 on a collision, -1 otherwise.
    ``reward_mode="rich"`` adds ``-1.0 * d - 0.3 * |theta|`` every step, with ``d`` the
    distance to the goal and ``theta`` the angle between heading and goal bearing after the
    action (the paper's rich reward).
    ``reward_mode="shaped"`` adds the potential-based shaping term
    ``F = gamma * Phi(s') - Phi(s)`` to the sparse reward (Ng, Harada and Russell 1999, the
    paper's reference for reward shaping), with ``Phi(s) = -c(s)``, ``c`` the oracle's
    shortest path from the pose to the goal in actions (``NO_PATH_STEPS`` where it finds
    none), times the step cost 1, and ``Phi = 0`` at terminal states (goal or collision),
    so that the discounted sum of ``F`` over an episode is ``gamma^T Phi(s_T) - Phi(s_0)``
    and the optimal policies of the shaped and the sparse reward are the same.
    ``-c`` is the sparse reward's undiscounted optimal value up to a constant, the
    potential Ng et al. recommend; unlike the Euclidean distance it does not lead into
    obstacles. ``gamma`` is ``shaping_gamma`` and must be the learner's discount.
    ``reward_mode="dense"`` (the reward of the ``rl_rich`` method) is the paper's rich
    reward with the oracle's geodesic path in place of the straight-line distance and
    heading error, and a crash charged what staying there for ever would cost: every step
    adds ``-distance_coef * c(s')`` (``c`` the oracle's path from the new pose in actions,
    ``NO_PATH_STEPS`` where it finds none, 0 in the goal), a collision
    ``-distance_coef * c(s) / (1 - gamma)`` with ``gamma = shaping_gamma``
    (``distance_coef`` = alpha, default 0.3). Why the oracle's path stays optimal, for
    any alpha > 0: along it ``c`` falls by one an action, as fast as any path can (up to
    the lattice's rounding), so it minimises every later step's distance cost as well as
    the time to the goal. Why a crash never pays more than going on: a crash at ``s``
    costs ``-100 - alpha c(s) / (1 - gamma)``, which at gamma = 0.99 is exactly
    ``sum_t gamma^t (-1 - alpha c(s))``, the step cost at ``s`` for ever, whereas the
    oracle's path from ``s`` costs less at every step (``c`` falls) and ends with +100:
    going on to the goal always returns more than crashing. A crash dearer than standing
    at ``s`` for ever (``-200 - ...``, or charged at ``c = NO_PATH_STEPS`` wherever it
    happens) was measured to make our PPO shun the walls and never find the doorway.

    ## Starting State

    The map's start pose, plus (VSSG) a uniform offset in x and y within the jitter square.

    ## Episode End

    Termination: the robot's centre comes within the goal radius (0.5 m) of the goal
    (``info["is_success"]``), or a forward move would make the footprint (a disc of radius
    0.4 m) touch an obstacle or wall (``info["collision"]``; the robot stays where it was).
    Truncation: 120 steps, added by the registered ``TimeLimit``.

    ## Info

    Every step: ``is_success``, ``collision``, ``pose`` ``(x, y, yaw)``. ``reset`` adds
    ``shortest_path_steps``: the number of actions the oracle policy needs from the start.

    ## Oracle cache

    ``oracle_cache_dir``: folder where the map's oracle lattice is cached on disk (read if
    present, written after a build). None (default) keeps it in memory only, so a plain
    ``gymnasium.make`` writes no file. The services and ``bgrl`` pass
    ``$BGRL_DATA_DIR/sim/oracle``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 8}

    def __init__(
        self,
        task: Task = "sssg",
        reward_mode: RewardMode = "sparse",
        map_path: str | Path | None = None,
        render_mode: str | None = None,
        *,
        render_width: int = rendering.FRAME_WIDTH,
        render_height: int = rendering.FRAME_HEIGHT,
        oracle_cache_dir: str | Path | None = None,
        shaping_gamma: float = SHAPING_GAMMA,
        distance_coef: float = DENSE_DISTANCE_COEF,
    ) -> None:
        if task not in ("sssg", "vssg"):
            raise ValueError(f"task must be 'sssg' or 'vssg', got {task!r}")
        if reward_mode not in REWARD_MODES:
            raise ValueError(f"reward_mode must be one of {REWARD_MODES}, got {reward_mode!r}")
        if not 0.0 < shaping_gamma <= 1.0:
            raise ValueError(f"shaping_gamma must be in (0, 1], got {shaping_gamma!r}")
        self.shaping_gamma = float(shaping_gamma)
        if not (math.isfinite(distance_coef) and distance_coef > 0.0):
            raise ValueError(f"distance_coef must be positive, got {distance_coef!r}")
        if reward_mode == "dense" and shaping_gamma >= 1.0:
            raise ValueError("the dense reward needs shaping_gamma < 1 (the crash's cost)")
        self.distance_coef = float(distance_coef)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        for name, size in (("render_width", render_width), ("render_height", render_height)):
            # pybullet aborts the whole process (std::bad_alloc) on a negative frame size.
            if (
                not isinstance(size, numbers.Integral)
                or isinstance(size, bool)
                or not 1 <= size <= MAX_RENDER_SIZE
            ):
                raise ValueError(
                    f"{name} must be an integer in [1, {MAX_RENDER_SIZE}] pixels, got {size!r}"
                )
        self.task: Task = task
        self.reward_mode: RewardMode = reward_mode
        self.render_mode = render_mode
        self.render_size = (int(render_width), int(render_height))
        self.map_path = Path(map_path) if map_path is not None else DEFAULT_MAP_PATH
        self.nav_map: NavMap = load_map(self.map_path)
        self.oracle = Oracle.for_map(self.nav_map, oracle_cache_dir)
        self.oracle.check_reachable(f"map file {self.map_path}")
        self._geometry = self.nav_map.geometry

        self.action_space = spaces.Discrete(N_ACTIONS)
        high = np.array(
            [RAY_LENGTH_M] * N_RAYS + [self.nav_map.diagonal, math.pi, math.pi], dtype=np.float32
        )
        low = np.array([0.0] * N_RAYS + [0.0, -math.pi, -math.pi], dtype=np.float32)
        self.observation_space = spaces.Box(low=low, high=high, dtype=np.float32)

        self._closed = False
        # a headless env casts its rays in the map's shared world (services.sim.world)
        self._shared_world = render_mode != "rgb_array"
        self._robot_id: int | None = None
        if self._shared_world:
            self._client, self._ray_z, self._ray_memo = acquire_shared_world(self.nav_map)
        else:
            self._ray_memo = RayMemo()
            self._client = bullet.connect()
            try:
                self._robot_id, self._ray_z = build_world(self._client, self.nav_map, husky=True)
            except BaseException:
                self._closed = True
                bullet.disconnect(self._client)
                raise
        self._start_yaw = self.nav_map.start.yaw
        # Ray end offsets per heading index: yaw = start yaw + k * 30 deg exactly.
        self._ray_offsets = [
            [
                (
                    RAY_LENGTH_M * math.cos(wrap_angle(self._start_yaw + k * TURN_STEP_RAD) + a),
                    RAY_LENGTH_M * math.sin(wrap_angle(self._start_yaw + k * TURN_STEP_RAD) + a),
                )
                for a in RAY_ANGLES_RAD.tolist()
            ]
            for k in range(_N_HEADINGS)
        ]
        self._goal = (self.nav_map.goal.x, self.nav_map.goal.y)
        self._goal_radius = self.nav_map.goal.radius
        self._x = self.nav_map.start.x
        self._y = self.nav_map.start.y
        self._heading = 0
        self._yaw = wrap_angle(self._start_yaw)
        self._clearance_bound = 0.0
        self._trajectory: list[tuple[float, float]] = []
        self._rays: tuple[float, ...] = (RAY_LENGTH_M,) * N_RAYS
        self._body_synced = False
        self._sssg_shortest_steps: int | None = None
        self._potential = 0.0

    def _cast_rays(self) -> None:
        """The rays from the current pose, cast or remembered (:class:`RayMemo`)."""
        pose = (self._x, self._y, self._heading)
        rays = self._ray_memo.get(pose)
        if rays is None:
            x, y, z = self._x, self._y, self._ray_z
            origin = [x, y, z]
            ends = [[x + dx, y + dy, z] for dx, dy in self._ray_offsets[self._heading]]
            hits = pybullet.rayTestBatch([origin] * N_RAYS, ends, physicsClientId=self._client)
            rays = tuple(hit[2] * RAY_LENGTH_M for hit in hits)
            self._ray_memo.remember(pose, rays)
        self._rays = rays

    def _observation(self) -> tuple[np.ndarray, float, float]:
        dx = self._goal[0] - self._x
        dy = self._goal[1] - self._y
        distance = math.hypot(dx, dy)
        bearing = math.atan2(dy, dx)
        obs = np.array([*self._rays, distance, bearing, self._yaw], dtype=np.float32)
        return obs, distance, bearing

    def _info(self, *, success: bool, collision: bool) -> dict[str, Any]:
        return {"is_success": success, "collision": collision, "pose": self.pose}

    # --------------------------------------------------------------- gym API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode (VSSG draws the start from ``self.np_random``)."""
        self._check_open("reset")
        super().reset(seed=seed)
        start = self.nav_map.start
        x, y = start.x, start.y
        if self.task == "vssg":
            half = self.nav_map.start_jitter / 2.0
            x += float(self.np_random.uniform(-half, half))
            y += float(self.np_random.uniform(-half, half))
        self._x, self._y = x, y
        self._heading = 0
        self._yaw = wrap_angle(self._start_yaw)
        self._clearance_bound = self._geometry.clearance(x, y)
        self._trajectory = [(x, y)]
        self._body_synced = False
        self._cast_rays()
        obs, _, _ = self._observation()
        info = self._info(success=False, collision=False)
        info["shortest_path_steps"] = self._shortest_path_steps()
        self._potential = -float(info["shortest_path_steps"]) * abs(STEP_REWARD)
        return obs, info

    def potential(self) -> float:
        """The shaping potential ``Phi`` of the current (non-terminal) pose: minus the
        oracle's shortest path to the goal, in actions (see Rewards)."""
        return -self.path_cost() * abs(STEP_REWARD)

    def path_cost(self) -> float:
        """``c(s)``: the oracle's shortest path from the current pose to the goal, in
        actions (``NO_PATH_STEPS`` where it finds none)."""
        steps = self.oracle.cost_to_go(self._x, self._y, self._yaw)
        return steps if math.isfinite(steps) else NO_PATH_STEPS

    def _shortest_path_steps(self) -> int:
        """The oracle policy's path length from the current pose (cached for SSSG)."""
        if self.task == "sssg" and self._sssg_shortest_steps is not None:
            return self._sssg_shortest_steps
        steps = self.oracle.cost_to_go(self._x, self._y, self._yaw)
        if not math.isfinite(steps):
            raise RuntimeError(f"the oracle finds no path from the start pose {self.pose}")
        if self.task == "sssg":
            self._sssg_shortest_steps = int(steps)
        return int(steps)

    def _forward_collides(self, nx: float, ny: float) -> bool:
        """Sweep the footprint disc along the move (as the oracle does), skipping the check
        while a lower bound on the clearance shows that the move cannot collide."""
        # Clearance is 1-Lipschitz: far from everything a 0.3 m move cannot collide.
        if self._clearance_bound - FORWARD_STEP_M >= FOOTPRINT_RADIUS_M:
            self._clearance_bound -= FORWARD_STEP_M
            return False
        if self._geometry.move_collides(self._x, self._y, nx, ny):
            return True
        self._clearance_bound = self._geometry.clearance(nx, ny)
        return False

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Execute one action; see the class docstring for rewards and termination."""
        self._check_open("step")
        try:
            a = int(action)
        except (TypeError, ValueError):
            raise ValueError(f"action must be 0, 1 or 2, got {action!r}") from None
        if not 0 <= a < N_ACTIONS or a != action:
            raise ValueError(f"action must be 0, 1 or 2, got {action!r}")
        collision = False
        if a == Action.FORWARD:
            nx = self._x + FORWARD_STEP_M * math.cos(self._yaw)
            ny = self._y + FORWARD_STEP_M * math.sin(self._yaw)
            if self._forward_collides(nx, ny):
                collision = True
            else:
                self._x, self._y = nx, ny
                self._trajectory.append((nx, ny))
                self._body_synced = False
                self._cast_rays()
        else:
            turn = 1 if a == Action.TURN_LEFT else -1
            self._heading = (self._heading + turn) % _N_HEADINGS
            self._yaw = wrap_angle(self._start_yaw + self._heading * TURN_STEP_RAD)
            self._body_synced = False
            self._cast_rays()
        obs, distance, bearing = self._observation()
        success = not collision and distance < self._goal_radius
        if collision:
            reward = COLLISION_REWARD
        elif success:
            reward = GOAL_REWARD
        else:
            reward = STEP_REWARD
        if self.reward_mode == "rich":
            heading_error = abs(wrap_angle(bearing - self._yaw))
            reward += RICH_DISTANCE_COEF * distance + RICH_HEADING_COEF * heading_error
        elif self.reward_mode == "shaped":
            next_potential = 0.0 if success or collision else self.potential()
            reward += self.shaping_gamma * next_potential - self._potential
            self._potential = next_potential
        elif self.reward_mode == "dense":
            # c of the pose after the step; on a collision the robot stayed where it was,
            # and the crash costs what staying there for ever would: c / (1 - gamma).
            cost = 0.0 if success else self.distance_coef * self.path_cost()
            reward -= cost / (1.0 - self.shaping_gamma) if collision else cost
        return (
            obs,
            reward,
            success or collision,
            False,
            self._info(success=success, collision=collision),
        )

    # ------------------------------------------------------------ extra API
    @property
    def pose(self) -> tuple[float, float, float]:
        """The robot's pose ``(x, y, yaw)`` in metres and radians."""
        return (self._x, self._y, self._yaw)

    @property
    def trajectory(self) -> list[tuple[float, float]]:
        """Positions visited in the current episode, the start first."""
        return list(self._trajectory)

    def optimal_actions(self) -> frozenset[int]:
        """The oracle's optimal actions in the current state."""
        return self.oracle.optimal_actions(self._x, self._y, self._yaw)

    @staticmethod
    def observation_cell(obs: np.ndarray, size_m: float) -> tuple[int, int, int]:
        """The pose cell an observation was taken at, from what the observation says (the
        count of PPO's exploration bonus): the robot's position relative to the goal (its
        distance ``obs[N_RAYS]`` and world bearing ``obs[N_RAYS + 1]``) on a ``size_m``
        grid, and its heading ``obs[N_RAYS + 2]`` in ``TURN_STEP_RAD`` steps (every turn
        changes it by one)."""
        distance, bearing, yaw = (float(v) for v in obs[N_RAYS : N_RAYS + 3])
        return (
            math.floor(-distance * math.cos(bearing) / size_m),
            math.floor(-distance * math.sin(bearing) / size_m),
            round(yaw / TURN_STEP_RAD) % _N_HEADINGS,
        )

    def _sync_body(self) -> None:
        if not self._body_synced and self._robot_id is not None:
            pybullet.resetBasePositionAndOrientation(
                self._robot_id,
                [self._x, self._y, 0.0],
                pybullet.getQuaternionFromEuler([0.0, 0.0, self._yaw]),
                physicsClientId=self._client,
            )
            self._body_synced = True

    def render(self) -> np.ndarray | None:
        """A third-person RGB frame (H, W, 3) uint8 with the rays drawn, or None."""
        if self.render_mode != "rgb_array":
            return None
        self._check_open("render")
        self._sync_body()
        return rendering.third_person_frame(
            self._client, self.pose, self._rays, self._ray_z, RAY_ANGLES_RAD, *self.render_size
        )

    def top_down_image(self, trajectory: Sequence[tuple[float, float]] | None = None) -> np.ndarray:
        """A top-down map (H, W, 3) uint8: obstacles, goal, robot and the trajectory.

        ``trajectory`` defaults to the positions of the current episode.
        """
        path = self._trajectory if trajectory is None else trajectory
        return rendering.top_down_image(self.nav_map, self.pose, path)

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise ClosedEnvironmentError(
                f"cannot {what}: this BrainNavEnv was closed; make a new env"
            )

    def __getstate__(self) -> dict[str, Any]:
        """Refused: a copy would share (and its ``close`` would end) this env's pybullet
        connection."""
        raise TypeError(
            "a BrainNavEnv holds a pybullet connection and cannot be copied or pickled; "
            "make another env with the same arguments (gymnasium.make) and reset it with the "
            "same seed: the same actions then give the same trajectory"
        )

    def close(self) -> None:
        """Release this env's pybullet world (a second call does nothing)."""
        if not self._closed:
            self._closed = True
            if self._shared_world:
                release_shared_world(self.nav_map)
            else:
                bullet.disconnect(self._client)
        super().close()
