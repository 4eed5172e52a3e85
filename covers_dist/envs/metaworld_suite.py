"""The Meta-World v3 symmetric task suite: base tasks, their exact g-transformed copies, rendering.

A transformed task ``g.T`` runs the base task's MuJoCo physics unchanged. The agent sees the
arm-free top-down image ``g(image)`` and the proprio ``[g(hand x, y), hand z, gripper]`` with
(x, y) measured from the symmetry centre (0, 0.6) (where the hand starts; button-press starts it
at y = 0.4); its action ``(dx, dy, dz, gripper)`` has (dx, dy) mapped by ``g^-1`` before it
reaches Meta-World. Reward and ``info["success"]`` are the base task's, so ``g.T`` is exactly
equivalent to ``T``. Where the task's spec knows Meta-World's success radius, ``info["target_ratio"]``
is the step's closest ``obj_to_target`` over that radius (<= 1 exactly on success): how far a
failed episode stayed from success, in radii (an evaluation's "misses").

Object and goal placement is drawn from each task's own Meta-World range with the env's seeded
generator (``reset(seed=...)``); no MT1 wrapper is involved, so nothing re-samples or overwrites
a task behind the agent's back. Object and goal positions are available to tests and evaluation
through :meth:`MetaWorldTask.task_state`, never in the observation.

Every task is observable: what decides success is visible in the first observation. Where a
task's spec holds a goal height (``goal_z``; Goal Reach, whose goal height Meta-World draws from
0.05..0.3 m and a top-down image cannot show), the goal is moved to that height right after
Meta-World's reset, everywhere Meta-World keeps it (``_target_pos``, the goal site, its own
observation vector), before the agent sees anything. ``observable=False`` keeps Meta-World's
sampling (for comparison in tests).

Base tasks live in a registry (:data:`TASKS`); :func:`register_task` adds any other Meta-World
v3 environment by name. Importing this module registers the ``metaworld`` suite with
:func:`covers_dist.envs.register_suite`.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..config import METAWORLD_MAX_PATH_LENGTH
from ..symmetry import GroupElement
from . import register_suite
from .layout import ObsLayout
from .metaworld_tasks import (
    TASKS,
    MetaWorldTaskSpec,
    PALETTES,
    apply_palette,
    apply_task_colors,
    metaworld_env_class,
    register_task,
    robot_bodies,
    table_geoms,
)
from .topdown_render import TopDownRasterizer
from .topdown_view import DISC_COLOR, TopDownView, disc_pixels

__all__ = [
    "MetaWorldTask",
    "MetaWorldTaskSpec",
    "TASKS",
    "register_task",
    "metaworld_task_names",
    "metaworld_layout",
    "make_metaworld_task",
    "register_metaworld_envs",
    "robot_bodies",
    "table_geoms",
    "SYMMETRY_CENTRE",
    "VIEW_HALF_WIDTH",
    "DISC_RADIUS",
    "DEFAULT_MAX_EPISODE_STEPS",
    "MIN_IMAGE_SIZE",
    "MAX_IMAGE_SIZE",
    "RENDER_BACKENDS",
]

#: The point of the table the group acts about: the hand's start (x, y) in metres.
SYMMETRY_CENTRE = (0.0, 0.6)
#: Half the side of the square view (metres): inside the table's retaining walls (y 0.22..0.98).
VIEW_HALF_WIDTH = 0.36
#: Radius of the blue gripper disc (metres).
DISC_RADIUS = 0.03
#: Suggested episode length for training on CPU (Meta-World's own limit is 500); the config's
#: ``env.max_episode_steps`` decides.
DEFAULT_MAX_EPISODE_STEPS = 150
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 32, 128
RENDER_BACKENDS = ("auto", "numpy", "egl", "osmesa")
_PROPRIO_BOUND = np.array([1.0, 1.0, 1.5, 1.0], dtype=np.float32)


def metaworld_task_names() -> tuple[str, ...]:
    """Names of the registered base tasks."""
    return tuple(TASKS)


#: Fixed proprio statistics for ``network.proprio_norm``: the hand's (x, y) about the symmetry centre
#: and its height about 0.15 m, in tenths of a metre (the view spans +-0.36 m, success radii are
#: 2-7 cm: a few centimetres become a few tenths at the network's input); the gripper opening
#: (0..1) to -1..1.
PROPRIO_SHIFT = (0.0, 0.0, 0.15, 0.5)
PROPRIO_SCALE = (10.0, 10.0, 10.0, 2.0)


def metaworld_layout(image_size: int = 64) -> ObsLayout:
    """Observations: image + proprio [x, y, z, gripper] (one planar pair); actions (dx, dy, dz, grip)."""
    return ObsLayout(
        image_size=image_size, proprio_dim=4, proprio_pairs=1, action_dim=4, action_pairs=1,
        proprio_shift=PROPRIO_SHIFT, proprio_scale=PROPRIO_SCALE,
    )  # fmt: skip


def _check_image_size(image_size: Any) -> int:
    if isinstance(image_size, bool) or not isinstance(image_size, (int, np.integer)):
        raise TypeError(f"image_size must be an integer, got {image_size!r}")
    if not MIN_IMAGE_SIZE <= image_size <= MAX_IMAGE_SIZE:
        raise ValueError(
            f"image_size={image_size} is out of range: Meta-World images are {MIN_IMAGE_SIZE}..{MAX_IMAGE_SIZE} px"
        )
    return int(image_size)


def _is_real(value: Any) -> bool:
    """A real number (numpy floats included), not a bool."""
    return isinstance(value, (int, float, np.floating)) and not isinstance(value, bool)


class MetaWorldTask(gym.Env):
    """One transformed Meta-World task ``g.T`` with arm-free top-down images.

    ``render_backend``: ``numpy`` (the default behind ``auto``: MuJoCo's geometry rasterized in
    numpy, no OpenGL) or ``egl`` / ``osmesa`` (MuJoCo's GL renderer with the same view).
    ``camera_shift`` / ``camera_shift_angle``: move the camera's (x, y) by ``camera_shift``
    metres in the direction ``camera_shift_angle`` degrees (counter-clockwise from +x), for
    robustness evaluation; the robot, the symmetry centre and the proprio do not move.
    ``observable``: apply the spec's fixed goal height (``goal_z``) at every reset (the default);
    ``False`` keeps Meta-World's own goal sampling, whose height the image cannot show.
    ``success_bonus``: added to the reward of every agent step on which the task succeeds
    (``info["success"]``); 0, the default, leaves Meta-World's reward as it is. ``success_bonus_once``:
    pay it only on the episode's first successful step. ``success_bonus_radius``: pay it only where
    the task's distance is within this fraction of its success radius (``info["target_ratio"] <=
    success_bonus_radius``); 1, the default, pays it on every success, a smaller value only on steps
    that go past the edge of success into it. ``palette``: ``task`` (each task's own object
    colours) or ``mono`` (every object and marker of every task in one grey,
    :func:`~covers_dist.envs.metaworld_tasks.apply_palette`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 80}

    def __init__(
        self,
        task: str = "reach-v3",
        g: GroupElement | str = "e",
        image_size: int = 64,
        max_episode_steps: int = DEFAULT_MAX_EPISODE_STEPS,
        render_backend: str = "auto",
        camera_shift: float = 0.0,
        camera_shift_angle: float = 0.0,
        render_mode: str | None = None,
        observable: bool = True,
        action_repeat: int = 1,
        success_bonus: float = 0.0,
        success_bonus_once: bool = False,
        success_bonus_radius: float = 1.0,
        palette: str = "task",
    ) -> None:
        if task not in TASKS:
            raise ValueError(f"unknown Meta-World task {task!r}; expected one of {list(TASKS)}")
        self.image_size = _check_image_size(image_size)
        steps_ok = isinstance(max_episode_steps, (int, np.integer)) and not isinstance(max_episode_steps, bool)
        if not steps_ok or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be an integer >= 1, got {max_episode_steps!r}")
        repeat_ok = isinstance(action_repeat, (int, np.integer)) and not isinstance(action_repeat, bool)
        if not repeat_ok or action_repeat < 1:
            raise ValueError(f"action_repeat must be an integer >= 1, got {action_repeat!r}")
        if max_episode_steps * action_repeat > METAWORLD_MAX_PATH_LENGTH:
            raise ValueError(
                f"max_episode_steps x action_repeat = {max_episode_steps * action_repeat} Meta-World steps; "
                f"Meta-World allows at most {METAWORLD_MAX_PATH_LENGTH} per episode"
            )
        if not _is_real(success_bonus) or not 0 <= success_bonus < math.inf:
            raise ValueError(f"success_bonus must be a finite number >= 0, got {success_bonus!r}")
        if not isinstance(success_bonus_once, bool):
            raise TypeError(f"success_bonus_once must be True or False, got {success_bonus_once!r}")
        if not _is_real(success_bonus_radius) or not 0 < success_bonus_radius <= 1:
            raise ValueError(f"success_bonus_radius must be a fraction in (0, 1], got {success_bonus_radius!r}")
        if success_bonus_radius < 1 and TASKS[task].success_radius is None:
            raise ValueError(
                f"success_bonus_radius={success_bonus_radius}: task {task!r} registers no success radius "
                "to take a fraction of"
            )
        if render_backend not in RENDER_BACKENDS:
            raise ValueError(f"render_backend must be one of {list(RENDER_BACKENDS)}, got {render_backend!r}")
        if not (isinstance(camera_shift, (int, float)) and math.isfinite(camera_shift) and camera_shift >= 0):
            raise ValueError(f"camera_shift must be a finite distance >= 0 (metres), got {camera_shift!r}")
        if palette not in PALETTES:
            raise ValueError(f"palette must be one of {list(PALETTES)}, got {palette!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not isinstance(observable, bool):
            raise TypeError(f"observable must be True or False, got {observable!r}")
        self.task, self.spec_entry = task, TASKS[task]
        self.observable = observable
        self.g = _element(g)
        self.g_inv = self.g.inverse()
        self.max_episode_steps = int(max_episode_steps)
        self.action_repeat = int(action_repeat)
        self.success_bonus = float(success_bonus)
        self.success_bonus_once = success_bonus_once
        self.success_bonus_radius = float(success_bonus_radius)
        self._bonus_paid = False
        self.render_mode = render_mode
        self.layout = metaworld_layout(self.image_size)
        self.observation_space = spaces.Dict(
            {
                "image": spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8),
                "proprio": spaces.Box(-_PROPRIO_BOUND, _PROPRIO_BOUND, (4,), np.float32),
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)

        self._mw = metaworld_env_class(task)()
        self._mw._set_task_called = True  # we place objects ourselves: no MT1 task, no re-sampling
        self._mw._freeze_rand_vec = False
        self._mw.seeded_rand_vec = True
        self._mw._partially_observable = False  # keep the goal in Meta-World's vector (scripted expert)
        self._mw.__dict__.pop("sawyer_observation_space", None)
        self._mw.max_path_length = self.max_episode_steps * self.action_repeat
        model = self._mw.model
        self._goal_z = self.spec_entry.goal_z if observable else None
        if self._goal_z is not None:
            _check_goal_site(self._mw, self.spec_entry)
        apply_task_colors(model, self.spec_entry)
        robot, table = robot_bodies(model), table_geoms(model)
        self.palette = palette
        apply_palette(model, palette, table, robot)
        angle = math.radians(camera_shift_angle)
        centre = (
            SYMMETRY_CENTRE[0] + camera_shift * math.cos(angle),
            SYMMETRY_CENTRE[1] + camera_shift * math.sin(angle),
        )
        self.view = TopDownView(centre, VIEW_HALF_WIDTH, self.image_size)
        self.render_backend = "numpy" if render_backend == "auto" else render_backend
        if self.render_backend == "numpy":
            self._renderer: Any = TopDownRasterizer(model, self._mw.data, self.view, robot, table)
        else:
            from .gl_render import GLTopDownRenderer

            self._renderer = GLTopDownRenderer(model, self._mw.data, self.view, robot, table, self.render_backend)
        self._set_element_tables()
        self._expert: Any = None
        self._t = -1  # no episode yet
        self._last_obs: dict[str, np.ndarray] | None = None
        self._mw_obs: np.ndarray | None = None

    # ---- the group element ---------------------------------------------------------------------
    def set_element(self, g: GroupElement | str) -> None:
        """Make this env the transformed task ``g.T`` of the same base task (as if built with ``g``).

        Building a Meta-World env costs ~0.25 s (model compile, static geometry); a worker that
        meets many elements of one task switches them instead. Takes effect at the next reset.
        """
        self.g = _element(g)
        self.g_inv = self.g.inverse()
        self._set_element_tables()
        self._t = -1  # the current episode's observations were for the old element

    def _set_element_tables(self) -> None:
        """Index tables of g on pixels, proprio and actions (pure functions of g and the size)."""
        size = self.image_size
        # image[i] = base[perm[i]]; base pixel b lands at dest[b]
        index = np.arange(size * size).reshape(size, size)
        self._pixel_perm = None if self.g.is_identity else self.g.apply_image(index).ravel()
        self._pixel_dest = None if self._pixel_perm is None else np.argsort(self._pixel_perm)
        self._scene_source: np.ndarray | None = None
        self._scene_g: np.ndarray | None = None
        # g on vectors whose first two entries are (x, y): out[i] = sign[i] * v[perm[i]]
        mat = self.g.matrix()
        self._vec_perm = np.array([int(np.flatnonzero(mat[0])[0]), int(np.flatnonzero(mat[1])[0]), 2, 3])
        self._vec_sign = np.array([mat[0].sum(), mat[1].sum(), 1, 1], dtype=np.float32)
        inv = self.g_inv.matrix()
        self._act_perm = np.array([int(np.flatnonzero(inv[0])[0]), int(np.flatnonzero(inv[1])[0]), 2, 3])
        self._act_sign = np.array([inv[0].sum(), inv[1].sum(), 1, 1], dtype=np.float32)

    # ---- gym API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._mw.np_random = self.np_random  # object/goal placement follows this env's seed
        mw_obs, _ = self._mw.reset()
        import mujoco

        if self._goal_z is not None:
            self._hold_goal_height(self._goal_z)
        mujoco.mj_forward(self._mw.model, self._mw.data)  # sites moved by reset_model take effect
        if self._goal_z is not None:
            mw_obs = self._mw_reset_obs()
        if hasattr(self._renderer, "invalidate"):
            self._renderer.invalidate()
        self._t = 0
        self._bonus_paid = False
        self._mw_obs = mw_obs
        obs = self._observation(mw_obs)
        return obs, {"success": 0.0}

    def _hold_goal_height(self, z: float) -> None:
        """Put the goal Meta-World just drew at height ``z``: the target that reward and success
        read, the goal site that is drawn (and that Meta-World re-places from the target after
        every step), and the reach distance Meta-World's v1 reward normalises by."""
        mw = self._mw
        target = np.array(mw._target_pos, dtype=np.float64)
        target[2] = z
        mw._target_pos = target
        mw.model.site("goal").pos = target
        if hasattr(mw, "maxReachDist"):
            mw.maxReachDist = float(np.linalg.norm(mw.init_tcp - target))

    def _mw_reset_obs(self) -> np.ndarray:
        """Meta-World's observation vector of the current (just reset) state, built the way its
        ``reset`` builds it: the previous frame equals the current one, the goal last."""
        mw = self._mw
        current = mw._get_curr_obs_combined_no_goal()
        mw._prev_obs = current.copy()
        goal = np.zeros(3) if mw._partially_observable else mw._get_pos_goal()
        return np.hstack((current, current, goal)).astype(np.float64)

    def step(self, action: np.ndarray):
        if self._t < 0:
            raise RuntimeError("call reset() before step()")
        if self._t >= self.max_episode_steps:
            raise RuntimeError(f"the episode ended after {self.max_episode_steps} steps; call reset()")
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape != (4,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 4 finite numbers (dx, dy, dz, gripper), got {action!r}")
        base = np.clip(a[self._act_perm] * self._act_sign, -1.0, 1.0)  # g^-1 on (dx, dy)
        reward, success, distance = 0.0, 0.0, math.inf
        for _ in range(self.action_repeat):  # the same action; one image after the last
            mw_obs, r, _, _, mw_info = self._mw.step(base)
            reward += float(r)
            success = max(success, float(mw_info["success"]))
            distance = min(distance, float(mw_info.get("obj_to_target", math.inf)))
        radius = self.spec_entry.success_radius
        ratio = distance / radius if radius is not None and math.isfinite(distance) else None
        if self.success_bonus_radius < 1:  # only steps past the edge, into the success region
            earned = 1.0 if ratio is not None and ratio <= self.success_bonus_radius else 0.0
        else:
            earned = success
        if earned > 0 and not (self.success_bonus_once and self._bonus_paid):
            reward += self.success_bonus * earned
            self._bonus_paid = True
        self._t += 1
        self._mw_obs = mw_obs
        obs = self._observation(mw_obs)
        info = {"success": success}
        if ratio is not None:
            info["target_ratio"] = ratio  # <= 1 exactly when Meta-World counts success
        return obs, reward, False, self._t >= self.max_episode_steps, info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return self._last_obs["image"].copy()

    def close(self) -> None:
        if getattr(self, "_renderer", None) is not None and hasattr(self._renderer, "close"):
            self._renderer.close()
        self._renderer = None
        if getattr(self, "_mw", None) is not None:
            self._mw.close()
        super().close()

    # ---- observation -----------------------------------------------------------------------------
    def render_base(self) -> np.ndarray:
        """The untransformed (identity-element) image of the current state."""
        return self._renderer.render(self._mw.tcp_center, DISC_RADIUS)

    def _observation(self, mw_obs: np.ndarray) -> dict[str, np.ndarray]:
        base_proprio = np.array(
            [mw_obs[0] - SYMMETRY_CENTRE[0], mw_obs[1] - SYMMETRY_CENTRE[1], mw_obs[2], mw_obs[3]], dtype=np.float32
        )
        proprio = base_proprio[self._vec_perm] * self._vec_sign  # g on the (x, y) pair: swaps and signs
        np.clip(proprio, -_PROPRIO_BOUND, _PROPRIO_BOUND, out=proprio)
        self._last_obs = {"image": self._image(), "proprio": proprio}
        return self._last_obs

    def _image(self) -> np.ndarray:
        """g(base image). The image is a permutation of the base image's pixels (the one
        GroupElement.apply_image applies): the scene is permuted once per redraw and the disc's
        base-frame pixels are painted at their permuted places."""
        size = self.image_size
        if not isinstance(self._renderer, TopDownRasterizer):
            base = self.render_base()
            return base if self._pixel_perm is None else base.reshape(-1, 3)[self._pixel_perm].reshape(size, size, 3)
        scene, _ = self._renderer.render_scene()
        if scene is not self._scene_source:
            self._scene_source = scene
            permuted = scene if self._pixel_perm is None else scene.reshape(-1, 3)[self._pixel_perm]
            self._scene_g = permuted.reshape(size, size, 3)
        image = self._scene_g.copy()
        disc = disc_pixels(self.view, self._mw.tcp_center, DISC_RADIUS)
        image.reshape(-1, 3)[disc if self._pixel_perm is None else self._pixel_dest[disc]] = DISC_COLOR
        return image

    # ---- for tests and evaluation (never part of the observation) -------------------------------
    def task_state(self) -> dict[str, np.ndarray]:
        """Positions relative to the symmetry centre: ``*_base`` in the base task, the rest seen through g.

        Keys: ``hand`` (the gripper's tool centre, xyz), ``object`` (Meta-World's object position,
        xyz), ``goal`` (xyz), each also as ``hand_base`` etc.
        """
        if self._t < 0:
            raise RuntimeError("call reset() first")
        centre = np.array([SYMMETRY_CENTRE[0], SYMMETRY_CENTRE[1], 0.0])
        base = {
            "hand": np.asarray(self._mw.tcp_center, dtype=np.float64) - centre,
            "object": np.asarray(self._mw._get_pos_objects()[:3], dtype=np.float64) - centre,
            "goal": np.asarray(self._mw._target_pos, dtype=np.float64) - centre,
        }
        out = {f"{k}_base": v for k, v in base.items()}
        out.update({k: self.g.apply_planar(v, 1) for k, v in base.items()})
        return out

    def expert_action(self) -> np.ndarray:
        """Meta-World's scripted policy for the base task, expressed in this task's frame (g applied)."""
        if self._mw_obs is None:
            raise RuntimeError("call reset() first")
        if self._expert is None:
            from metaworld.policies import ENV_POLICY_MAP

            if self.task not in ENV_POLICY_MAP:
                raise ValueError(f"Meta-World has no scripted policy for {self.task!r}")
            self._expert = ENV_POLICY_MAP[self.task]()
        with warnings.catch_warnings():  # Meta-World warns that its own gains exceed the action range
            warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")
            raw = self._expert.get_action(self._mw_obs)
        base = np.clip(np.asarray(raw, dtype=np.float32), -1.0, 1.0)
        return self.layout.transform_action(self.g, base).astype(np.float32)

    @property
    def renderer(self) -> Any:
        """The base-view renderer (:class:`TopDownRasterizer` or :class:`GLTopDownRenderer`)."""
        return self._renderer

    @property
    def unwrapped_metaworld(self) -> Any:
        """The underlying Meta-World environment (physics of the base task)."""
        return self._mw


def _element(g: Any) -> GroupElement:
    element = GroupElement.from_name(g) if isinstance(g, str) else g
    if not isinstance(element, GroupElement):
        raise TypeError(f"g must be a GroupElement or an element name, got {g!r}")
    return element


def _check_goal_site(mw: Any, spec: MetaWorldTaskSpec) -> None:
    """A fixed goal height needs the goal to be the world-body site ``goal`` placed from
    ``_target_pos`` (as in reach-v3); other goals (a button's hole, a drawer's handle) are derived
    from bodies and cannot be moved alone."""
    import mujoco
    from metaworld.sawyer_xyz_env import SawyerXYZEnv

    sid = mujoco.mj_name2id(mw.model, mujoco.mjtObj.mjOBJ_SITE, "goal")
    # Meta-World's own site config, [("goal", _target_pos)], unless the env replaces it
    placed_from_target = type(mw)._target_site_config is SawyerXYZEnv._target_site_config
    if sid < 0 or int(mw.model.site_bodyid[sid]) != 0 or not placed_from_target:
        raise ValueError(
            f"task {spec.name}: goal_z needs the goal to be the world-body site 'goal' placed from the target"
        )


def make_metaworld_task(
    task: str,
    g: GroupElement | str = "e",
    image_size: int = 64,
    max_episode_steps: int = DEFAULT_MAX_EPISODE_STEPS,
    env_cfg: Any = None,
    **_: Any,
) -> MetaWorldTask:
    """The suite factory used by :func:`covers_dist.envs.make_task` (reads backend and camera shift)."""
    return MetaWorldTask(
        task,
        g,
        image_size=image_size,
        max_episode_steps=max_episode_steps,
        render_backend=getattr(env_cfg, "render_backend", "auto"),
        camera_shift=float(getattr(env_cfg, "camera_shift", 0.0)),
        camera_shift_angle=float(getattr(env_cfg, "camera_shift_angle", 0.0)),
        action_repeat=int(getattr(env_cfg, "action_repeat", 1)),
        success_bonus=float(getattr(env_cfg, "success_bonus", 0.0)),
        success_bonus_once=bool(getattr(env_cfg, "success_bonus_once", False)),
        success_bonus_radius=float(getattr(env_cfg, "success_bonus_radius", 1.0)),
        palette=str(getattr(env_cfg, "palette", "task")),
    )


_ENV_ID = "CoversDist/MetaWorld-{}"


def register_metaworld_envs() -> dict[str, str]:
    """Register the base tasks with gymnasium (idempotent); returns {task: env id}."""
    ids = {}
    for task in TASKS:
        env_id = _ENV_ID.format(task)
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=MetaWorldTask, kwargs={"task": task})
        ids[task] = env_id
    return ids


register_suite("metaworld", metaworld_task_names, metaworld_layout, make_metaworld_task)
