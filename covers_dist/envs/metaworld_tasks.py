"""The registry of Meta-World base tasks (task groups) and how each is drawn.

A base task is a Meta-World v3 environment name plus drawing details: colour overrides for named
geoms/sites (so that objects and goal markers stay distinct at 64 px) and marker sites to hide;
an optional fixed goal height (``goal_z``) for tasks whose sampled goal height the top-down image
cannot show; and the positions that decide success (``success_state``), which the observability
check (:mod:`covers_dist.envs.observability`) requires to be visible.
:func:`register_task` adds any Meta-World v3 environment; the four tasks of the COVERS paper are
registered on import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np

__all__ = [
    "MetaWorldTaskSpec",
    "TASKS",
    "register_task",
    "metaworld_env_class",
    "robot_bodies",
    "table_geoms",
    "apply_task_colors",
    "apply_palette",
    "PALETTES",
    "MONO_COLOR",
    "SUCCESS_STATE_KEYS",
]

#: Positions of :meth:`MetaWorldTask.task_state` that a spec's ``success_state`` may name.
SUCCESS_STATE_KEYS = ("hand", "object", "goal")


@dataclass(frozen=True)
class MetaWorldTaskSpec:
    """A base task group: a Meta-World v3 environment and how it is drawn."""

    name: str
    label: str
    #: rgb (0..1) overrides for named geoms/sites, so that objects and goal markers stay distinct
    colors: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: named sites not drawn (markers that do not mark anything in this task)
    hidden_sites: tuple[str, ...] = ()
    #: the goal's height (world z, metres) is held at this value at every reset, in place of the
    #: height Meta-World draws; ``None`` keeps Meta-World's goal. For goals that are the world-body
    #: site ``goal`` (reach-v3, push-v3, pick-place-v3, ...): a top-down image cannot show a
    #: sampled height, and success must not depend on what no observation carries.
    goal_z: float | None = None
    #: the positions (keys of ``MetaWorldTask.task_state()``) that decide success besides the
    #: hand, whose (x, y, z) the proprio carries; each must be visible at reset (the observability
    #: check holds them to it)
    success_state: tuple[str, ...] = ("object", "goal")
    #: Meta-World's success radius on ``info["obj_to_target"]`` (metres): success is that distance
    #: at or under it. The env reports the distance over the radius per step, so an evaluation can
    #: say how far a failed episode stayed from success; ``None``: no ratio is reported.
    success_radius: float | None = None


TASKS: dict[str, MetaWorldTaskSpec] = {}


def metaworld_env_class(name: str) -> type:
    """The Meta-World v3 environment class called ``name``."""
    known = _all_v3_envs()
    if name not in known:
        raise ValueError(f"unknown Meta-World v3 environment {name!r}; expected one of {sorted(known)}")
    return known[name]


def _all_v3_envs() -> dict[str, type]:
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return ALL_V3_ENVIRONMENTS


def register_task(
    name: str,
    label: str | None = None,
    colors: dict[str, tuple[float, float, float]] | None = None,
    hidden_sites: tuple[str, ...] = (),
    goal_z: float | None = None,
    success_state: tuple[str, ...] = ("object", "goal"),
    success_radius: float | None = None,
) -> MetaWorldTaskSpec:
    """Add the Meta-World v3 environment ``name`` (e.g. ``push-v3``) as a base task group.

    ``goal_z``: hold the goal's height at this world z (metres) at every reset (see
    :class:`MetaWorldTaskSpec`). ``success_radius``: Meta-World's success threshold on
    ``obj_to_target`` (metres), for the per-step ``info["target_ratio"]``. ``success_state``: the
    positions besides the hand that decide success, a subset of :data:`SUCCESS_STATE_KEYS`.
    """
    known = _all_v3_envs()
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"unknown Meta-World v3 environment {name!r}; expected one of {sorted(known)}")
    if goal_z is not None:
        if isinstance(goal_z, bool) or not isinstance(goal_z, (int, float)) or not math.isfinite(goal_z):
            raise ValueError(f"goal_z must be a finite height in metres or None, got {goal_z!r}")
        goal_z = float(goal_z)
    success_state = tuple(success_state)
    unknown = [k for k in success_state if k not in SUCCESS_STATE_KEYS]
    if not success_state or unknown or len(set(success_state)) != len(success_state):
        raise ValueError(
            f"success_state must name distinct positions out of {SUCCESS_STATE_KEYS}, got {success_state!r}"
        )
    if success_radius is not None:
        number = isinstance(success_radius, (int, float)) and not isinstance(success_radius, bool)
        if not number or not 0 < success_radius < math.inf:
            raise ValueError(f"success_radius must be a positive distance in metres or None, got {success_radius!r}")
        success_radius = float(success_radius)
    spec = MetaWorldTaskSpec(
        name,
        label or name,
        dict(colors or {}),
        tuple(hidden_sites),
        goal_z=goal_z,
        success_state=success_state,
        success_radius=success_radius,
    )
    TASKS[name] = spec
    return spec


# Success, read from each env's evaluate_state / compute_reward (metaworld 3.1.1):
# - reach-v3: ||tcp - _target_pos|| <= 0.05. The puck ("object") is placed but never read by the
#   reward or by success, so only the goal counts. Meta-World draws the goal's z from 0.05..0.3,
#   which the top-down image cannot show; it is held at 0.15 m, the middle of that range.
# - button-press-topdown-v3: |_target_pos.z - object.z| <= 0.024 with _target_pos the "hole"
#   site of the button box and object the button top; the box is placed at a fixed z (0.115).
# - drawer-close-v3: ||object - _target_pos|| <= 0.065 with object the drawer handle and
#   _target_pos the closed handle position; the drawer case is placed at a fixed z (0).
# - plate-slide-v3: ||object - _target_pos|| <= 0.07 with object the puck (plate) and
#   _target_pos the goal cage position, drawn with a fixed z (0).
register_task(
    "reach-v3", "Goal Reach", colors={"goal": (1.0, 0.85, 0.0)}, goal_z=0.15, success_state=("goal",), success_radius=0.05
)
register_task("button-press-topdown-v3", "Button Press", success_state=("object", "goal"), success_radius=0.024)
register_task("drawer-close-v3", "Drawer Close", success_state=("object", "goal"), success_radius=0.065)
register_task("plate-slide-v3", "Plate Slide", hidden_sites=("goal",), success_state=("object", "goal"), success_radius=0.07)


def robot_bodies(model: Any) -> set[int]:
    """Body ids of the Sawyer robot (the root of the hand's tree) and the mocap body that drives it."""
    robot = {int(model.body_rootid[model.body("hand").id])}
    return robot | {b for b in range(model.nbody) if model.body_mocapid[b] >= 0}


def table_geoms(model: Any) -> set[int]:
    """Geom ids of the table (drawn in one uniform colour instead of the wood texture)."""
    return {i for i in range(model.ngeom) if model.geom_bodyid[i] == model.body("tablelink").id}


def apply_task_colors(model: Any, spec: MetaWorldTaskSpec) -> None:
    """Recolour and hide a task's named geoms/sites in ``model`` (drawing only; physics unchanged)."""
    import mujoco

    for name, rgb in spec.colors.items():
        rgba = np.append(np.asarray(rgb, dtype=np.float32), 1.0)
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
        if gid < 0 and sid < 0:
            raise ValueError(f"task {spec.name}: no geom or site named {name!r} to colour")
        if gid >= 0:
            model.geom_rgba[gid] = rgba
        if sid >= 0:
            model.site_rgba[sid] = rgba
    for name in spec.hidden_sites:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
        if sid < 0:
            raise ValueError(f"task {spec.name}: no site named {name!r} to hide")
        model.site_rgba[sid, 3] = 0.0


#: Colour schemes of the suite (``env.palette``): ``task`` draws each task's objects in its own
#: colours (the defaults above), ``mono`` draws every object and marker of every task in one grey.
PALETTES: tuple[str, ...] = ("task", "mono")

#: The ``mono`` palette's one colour (RGB in [0, 1]): a light grey on the grey table
#: (TABLE_COLOR = 100/255). Lit from above it stays within the table's bin of the colour histogram's
#: 4 levels per channel (0-127 of 255), so that histogram sees table and objects as one colour, while
#: the contrast (about 20 of 255 grey levels) is visible to a network.
MONO_COLOR = (0.47, 0.47, 0.47)


def apply_palette(model: Any, palette: str, skip_geoms: set[int], skip_bodies: set[int]) -> None:
    """Recolour ``model`` for ``palette`` (one of :data:`PALETTES`; drawing only, physics unchanged).

    ``mono``: every geom and site with a visible colour (alpha > 0) takes :data:`MONO_COLOR`,
    except the geoms in ``skip_geoms`` (the table) and anything of the bodies ``skip_bodies``
    (the robot); materials are detached so the colour is the geom's own. The light becomes flat
    (the headlight's ambient term alone, as bright as the table lit from above was): a face is
    drawn in its own colour whatever its slope, so no shade of a slanted face tells one object's
    shape from another's by colour. Only the silhouettes and the layout remain."""
    if palette not in PALETTES:
        raise ValueError(f"palette must be one of {list(PALETTES)}, got {palette!r}")
    if palette == "task":
        return
    rgb = np.asarray(MONO_COLOR, dtype=np.float32)
    for i in range(model.ngeom):
        if i in skip_geoms or int(model.geom_bodyid[i]) in skip_bodies or model.geom_rgba[i, 3] <= 0:
            continue
        model.geom_matid[i] = -1
        model.geom_rgba[i, :3] = rgb
    for i in range(model.nsite):
        if int(model.site_bodyid[i]) in skip_bodies or model.site_rgba[i, 3] <= 0:
            continue
        model.site_matid[i] = -1
        model.site_rgba[i, :3] = rgb
    _flatten_light(model)


def _flatten_light(model: Any) -> None:
    """Replace the scene's lights by a uniform ambient light as bright as an upward face saw
    (the headlight and every active light's ambient and diffuse terms, as both renderers light)."""
    from .topdown_render import light_setup

    ambient, dirs, diffuse = light_setup(model)
    level = ambient + float(np.maximum(dirs[:, 2], 0.0) @ diffuse)
    head = model.vis.headlight
    head.active = 1
    head.ambient[:] = level
    head.diffuse[:] = 0.0
    model.light_active[:] = 0
