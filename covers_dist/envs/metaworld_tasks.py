"""The registry of Meta-World base tasks (task groups) and how each is drawn.

A base task is a Meta-World v3 environment name plus drawing details: colour overrides for named
geoms/sites (so that objects and goal markers stay distinct at 64 px) and marker sites to hide.
:func:`register_task` adds any Meta-World v3 environment; the four tasks of the COVERS paper are
registered on import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
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
]


@dataclass(frozen=True)
class MetaWorldTaskSpec:
    """A base task group: a Meta-World v3 environment and how it is drawn."""

    name: str
    label: str
    #: rgb (0..1) overrides for named geoms/sites, so that objects and goal markers stay distinct
    colors: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: named sites not drawn (markers that do not mark anything in this task)
    hidden_sites: tuple[str, ...] = ()


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
) -> MetaWorldTaskSpec:
    """Add the Meta-World v3 environment ``name`` (e.g. ``push-v3``) as a base task group."""
    known = _all_v3_envs()
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"unknown Meta-World v3 environment {name!r}; expected one of {sorted(known)}")
    spec = MetaWorldTaskSpec(name, label or name, dict(colors or {}), tuple(hidden_sites))
    TASKS[name] = spec
    return spec


register_task("reach-v3", "Goal Reach", colors={"goal": (1.0, 0.85, 0.0)})
register_task("button-press-topdown-v3", "Button Press")
register_task("drawer-close-v3", "Drawer Close")
register_task("plate-slide-v3", "Plate Slide", hidden_sites=("goal",))


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
