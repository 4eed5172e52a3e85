"""Toy symmetric tasks in pure numpy: a point robot seen from above.

Three visually distinct task groups live on the square arena [-1, 1]^2:

* ``reach``: move the blue agent onto the red goal disc.
* ``push``: push the green block onto the yellow target ring.
* ``avoid``: reach the orange goal without entering the purple obstacle between it and the start.

Each base task places its objects in one octant of the arena (so the eight elements of D4 give
eight visibly different, yet exactly equivalent, tasks). A transformed task ``g.T`` runs the base
task's dynamics unchanged: the agent sees ``g(image)`` and ``g(proprio)``, its action (dx, dy) is
mapped by ``g^-1`` before it reaches the dynamics, and rewards and success are the base task's.

Observations: ``{"image": uint8 (S, S, 3), "proprio": float32 [x, y, vx, vy]}`` (two planar
pairs). Action: float32 (dx, dy) in [-1, 1]^2 (one planar pair). Episodes are truncated after
``max_episode_steps`` (default 50) and never terminate early; ``info["success"]`` is 1.0 while
the goal condition holds.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..symmetry import GroupElement
from .layout import ObsLayout

__all__ = ["ToyTask", "TOY_TASKS", "toy_layout", "register_toy_envs"]

TOY_TASKS: tuple[str, ...] = ("reach", "push", "avoid")

BACKGROUND = np.array([40, 40, 40], dtype=np.uint8)
COLORS = {
    "agent": np.array([30, 60, 255], dtype=np.uint8),
    "reach_goal": np.array([230, 40, 40], dtype=np.uint8),
    "block": np.array([40, 200, 60], dtype=np.uint8),
    "target": np.array([240, 220, 40], dtype=np.uint8),
    "avoid_goal": np.array([255, 140, 0], dtype=np.uint8),
    "obstacle": np.array([150, 50, 200], dtype=np.uint8),
}
AGENT_RADIUS = 0.08
GOAL_RADIUS = 0.1
BLOCK_RADIUS = 0.1
TARGET_RADIUS = 0.16
OBSTACLE_RADIUS = 0.16
MAX_SPEED = 0.1
SUCCESS_DIST = 0.1


def toy_layout(image_size: int = 32) -> ObsLayout:
    """The observation/action layout of every toy task."""
    return ObsLayout(image_size=image_size, proprio_dim=4, proprio_pairs=2, action_dim=2, action_pairs=1)


class ToyTask(gym.Env):
    """One toy task ``g.T``: base task ``task`` seen through the D4 element ``g``."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        task: str = "reach",
        g: GroupElement | str = "e",
        image_size: int = 32,
        max_episode_steps: int = 50,
        render_mode: str | None = None,
    ) -> None:
        if task not in TOY_TASKS:
            raise ValueError(f"unknown toy task {task!r}; expected one of {list(TOY_TASKS)}")
        if not isinstance(image_size, int) or image_size < 8 or image_size % 2:
            raise ValueError(f"toy image_size must be an even integer >= 8, got {image_size!r}")
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = task
        self.g = GroupElement.from_name(g) if isinstance(g, str) else g
        self.g_inv = self.g.inverse()
        self.image_size = image_size
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self.layout = toy_layout(image_size)
        self.observation_space = spaces.Dict(
            {
                "image": spaces.Box(0, 255, (image_size, image_size, 3), np.uint8),
                "proprio": spaces.Box(-1.0, 1.0, (4,), np.float32),
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        # pixel-centre coordinates: x right, y up (see covers_dist.symmetry)
        c = (image_size - 1) / 2.0
        idx = np.arange(image_size, dtype=np.float64)
        scale = 2.0 / image_size
        self._xs = ((idx - c) * scale)[None, :]
        self._ys = ((c - idx) * scale)[:, None]
        self._pix = scale
        self._t = 0
        self._agent = np.zeros(2)
        self._vel = np.zeros(2)
        self._goal = np.zeros(2)
        self._block = np.zeros(2)
        self._obstacle = np.zeros(2)
        self._touched = False

    # ---- gym API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        self._t = 0
        self._touched = False
        self._agent = rng.uniform(-0.05, 0.05, size=2)
        self._vel = np.zeros(2)
        if self.task == "reach":
            self._goal = np.array([rng.uniform(0.5, 0.8), rng.uniform(0.1, 0.35)])
        elif self.task == "push":
            self._block = np.array([rng.uniform(0.25, 0.35), rng.uniform(0.05, 0.15)])
            self._goal = np.array([rng.uniform(0.65, 0.8), rng.uniform(0.2, 0.35)])
        else:  # avoid
            self._goal = np.array([rng.uniform(0.6, 0.8), rng.uniform(0.1, 0.3)])
            self._obstacle = 0.5 * self._goal + rng.uniform(-0.03, 0.03, size=2)
        return self._observation(), self._info()

    def step(self, action: np.ndarray):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 2 finite numbers, got {action!r}")
        base_action = np.clip(self.g_inv.apply_vectors(a), -1.0, 1.0)
        prev = self._agent.copy()
        self._agent = np.clip(self._agent + MAX_SPEED * base_action, -1.0, 1.0)
        self._vel = self._agent - prev
        if self.task == "push":
            self._push_block()
        if self.task == "avoid" and np.linalg.norm(self._agent - self._obstacle) < OBSTACLE_RADIUS:
            self._touched = True
        self._t += 1
        reward = self._reward()
        truncated = self._t >= self.max_episode_steps
        return self._observation(), reward, False, truncated, self._info()

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self.g.apply_image(self._render_base())

    # ---- task logic ------------------------------------------------------------------------
    def _push_block(self) -> None:
        d = self._block - self._agent
        dist = float(np.linalg.norm(d))
        reach = AGENT_RADIUS + BLOCK_RADIUS
        if dist < reach:
            direction = d / dist if dist > 1e-9 else self._vel / max(np.linalg.norm(self._vel), 1e-9)
            self._block = np.clip(self._agent + direction * reach, -1.0, 1.0)

    def _success(self) -> bool:
        if self.task == "push":
            return bool(np.linalg.norm(self._block - self._goal) < SUCCESS_DIST)
        near = bool(np.linalg.norm(self._agent - self._goal) < SUCCESS_DIST)
        return near and not (self.task == "avoid" and self._touched)

    def _reward(self) -> float:
        if self.task == "reach":
            return float(-np.linalg.norm(self._agent - self._goal))
        if self.task == "push":
            return float(
                -np.linalg.norm(self._block - self._goal) - 0.5 * np.linalg.norm(self._agent - self._block)
            )
        inside = np.linalg.norm(self._agent - self._obstacle) < OBSTACLE_RADIUS
        return float(-np.linalg.norm(self._agent - self._goal) - (1.0 if inside else 0.0))

    def _info(self) -> dict[str, Any]:
        return {"success": float(self._success())}

    # ---- observation -----------------------------------------------------------------------
    def _disc(self, img: np.ndarray, centre: np.ndarray, radius: float, color: np.ndarray) -> None:
        mask = (self._xs - centre[0]) ** 2 + (self._ys - centre[1]) ** 2 <= radius * radius
        img[mask] = color

    def _ring(self, img: np.ndarray, centre: np.ndarray, radius: float, color: np.ndarray) -> None:
        d2 = (self._xs - centre[0]) ** 2 + (self._ys - centre[1]) ** 2
        inner = max(radius - 1.5 * self._pix, 0.0)
        img[(d2 <= radius * radius) & (d2 >= inner * inner)] = color

    def _render_base(self) -> np.ndarray:
        s = self.image_size
        img = np.empty((s, s, 3), dtype=np.uint8)
        img[:] = BACKGROUND
        if self.task == "reach":
            self._disc(img, self._goal, GOAL_RADIUS, COLORS["reach_goal"])
        elif self.task == "push":
            self._ring(img, self._goal, TARGET_RADIUS, COLORS["target"])
            self._disc(img, self._block, BLOCK_RADIUS, COLORS["block"])
        else:
            self._disc(img, self._obstacle, OBSTACLE_RADIUS, COLORS["obstacle"])
            self._disc(img, self._goal, GOAL_RADIUS, COLORS["avoid_goal"])
        self._disc(img, self._agent, AGENT_RADIUS, COLORS["agent"])
        return img

    def _observation(self) -> dict[str, np.ndarray]:
        base_proprio = np.concatenate([self._agent, self._vel])
        return {
            "image": self.g.apply_image(self._render_base()),
            "proprio": self.layout.transform_proprio(self.g, base_proprio).astype(np.float32),
        }

    # ---- introspection (for tests and evaluation; never shown to the agent) -----------------
    def base_state(self) -> dict[str, np.ndarray]:
        return {
            "agent": self._agent.copy(),
            "goal": self._goal.copy(),
            "block": self._block.copy(),
            "obstacle": self._obstacle.copy(),
        }


_ENV_IDS = {"reach": "CoversDist/ToyReach-v0", "push": "CoversDist/ToyPush-v0", "avoid": "CoversDist/ToyAvoid-v0"}


def register_toy_envs() -> dict[str, str]:
    """Register the toy tasks with gymnasium (idempotent); returns {task: env id}."""
    for task, env_id in _ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=ToyTask, kwargs={"task": task})
    return dict(_ENV_IDS)
