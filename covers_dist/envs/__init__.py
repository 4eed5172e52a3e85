"""Task families: pure-numpy toy tasks and (lazily imported) the Meta-World suite.

:func:`make_task` is the one factory the runtime uses: ``make_task(env_cfg, task, g, seed)``
returns a gymnasium env for the transformed task ``g.T``. Suites register themselves in
:data:`SUITES`; the Meta-World suite is imported only when asked for, so toy-only code never
imports MuJoCo.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable

import gymnasium as gym

from ..symmetry import GroupElement
from .layout import ObsLayout, transform_obs
from .toy import TOY_TASKS, ToyTask, register_toy_envs, toy_layout

__all__ = ["ObsLayout", "transform_obs", "make_task", "task_names", "suite_layout", "SUITES", "register_suite"]


class _Suite:
    def __init__(
        self,
        names: Callable[[], tuple[str, ...]],
        layout: Callable[[int], ObsLayout],
        make: Callable[..., gym.Env],
    ) -> None:
        self.names, self.layout, self.make = names, layout, make


def _make_toy(task: str, g: GroupElement, image_size: int, max_episode_steps: int, **_: Any) -> gym.Env:
    return ToyTask(task=task, g=g, image_size=image_size, max_episode_steps=max_episode_steps)


SUITES: dict[str, _Suite] = {"toy": _Suite(lambda: TOY_TASKS, toy_layout, _make_toy)}
_LAZY_SUITES = {"metaworld": "covers_dist.envs.metaworld_suite"}


def register_suite(
    name: str,
    names: Callable[[], tuple[str, ...]],
    layout: Callable[[int], ObsLayout],
    make: Callable[..., gym.Env],
) -> None:
    """Add a task family (used by the Meta-World suite module when it is imported)."""
    SUITES[name] = _Suite(names, layout, make)


def _suite(name: str) -> _Suite:
    if name not in SUITES and name in _LAZY_SUITES:
        importlib.import_module(_LAZY_SUITES[name])
    if name not in SUITES:
        raise ValueError(f"unknown task suite {name!r}; expected one of {sorted(set(SUITES) | set(_LAZY_SUITES))}")
    return SUITES[name]


def task_names(suite: str) -> tuple[str, ...]:
    """Base task names of a suite."""
    return _suite(suite).names()


def suite_layout(suite: str, image_size: int) -> ObsLayout:
    """Observation/action layout of a suite at an image size."""
    return _suite(suite).layout(image_size)


def make_task(env_cfg: Any, task: str, g: GroupElement | str = "e", seed: int | None = None) -> gym.Env:
    """Build the transformed task ``g.T`` of base task ``task`` as configured by ``env_cfg``.

    ``env_cfg`` is a :class:`covers_dist.config.EnvConfig`. Unknown task names raise a
    ``ValueError`` that lists the valid ones. ``seed`` (if given) seeds the first reset.
    """
    suite = _suite(env_cfg.suite)
    if task not in suite.names():
        raise ValueError(f"unknown {env_cfg.suite} task {task!r}; expected one of {list(suite.names())}")
    element = GroupElement.from_name(g) if isinstance(g, str) else g
    env = suite.make(
        task,
        element,
        image_size=env_cfg.image_size,
        max_episode_steps=env_cfg.max_episode_steps,
        env_cfg=env_cfg,
    )
    if seed is not None:
        env.reset(seed=seed)
    return env


register_toy_envs()
