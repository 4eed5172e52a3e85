"""MuJoCo GL rendering: backend choice, the arm-free orthographic camera, and the stock top view.

MuJoCo picks its OpenGL platform from ``MUJOCO_GL`` when it is imported: ``egl`` (headless EGL,
software rendering on a CPU machine, the GPU on a GPU machine) or ``osmesa`` (software OSMesa).
:func:`select_gl_backend` chooses one that works, probing each candidate in a short-lived
subprocess (a failed GL start-up can leave a process unusable), and raises a clear
``RuntimeError`` naming what failed when none does. :func:`default_gl_environment` sets
``MUJOCO_GL`` for a command-line process before anything imports mujoco.

Every renderer here owns one ``mujoco.Renderer`` (one GL context) and makes it current before
each frame; ``close()`` frees it. That avoids the black-frame bug, where freeing an old context
after a new one became current left the new one rendering zeros.
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys
from collections.abc import MutableMapping
from typing import Any

import numpy as np

from .topdown_render import subtree_bodies
from .topdown_view import TABLE_COLOR, TopDownView, draw_disc

__all__ = [
    "GL_BACKENDS",
    "default_gl_environment",
    "probe_gl_backend",
    "select_gl_backend",
    "GLTopDownRenderer",
    "StockTopViewRenderer",
]

GL_BACKENDS: tuple[str, ...] = ("egl", "osmesa")
_PROBE = (
    "import mujoco, numpy as np\n"
    "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"1\"/></worldbody></mujoco>')\n"
    "r = mujoco.Renderer(m, 8, 8); d = mujoco.MjData(m); mujoco.mj_forward(m, d)\n"
    "r.update_scene(d); img = r.render(); r.close()\n"
    "assert img.shape == (8, 8, 3)\n"
)


_GL_LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa"}


def default_gl_environment(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM`` to match) unless set; returns ``MUJOCO_GL``.

    The default is the first of egl, osmesa whose library is installed (none: left unset). A
    value set by the user is kept. Does nothing once mujoco is imported (it has read the variable).
    """
    env = os.environ if environ is None else environ
    if "mujoco" in sys.modules:
        return env.get("MUJOCO_GL")
    if "MUJOCO_GL" not in env:
        import ctypes.util

        found = next((name for name, lib in _GL_LIBRARIES.items() if ctypes.util.find_library(lib)), None)
        if found is None:
            return None
        env["MUJOCO_GL"] = found
    backend = env["MUJOCO_GL"]
    if backend in GL_BACKENDS:
        env.setdefault("PYOPENGL_PLATFORM", backend)
    return backend


def probe_gl_backend(name: str, timeout_s: float = 60.0) -> str | None:
    """Try to render one frame with ``MUJOCO_GL=name`` in a subprocess; None if it works, else why not."""
    if name not in GL_BACKENDS:
        raise ValueError(f"unknown GL backend {name!r}; expected one of {list(GL_BACKENDS)}")
    env = dict(os.environ, MUJOCO_GL=name, PYOPENGL_PLATFORM=name)
    try:
        res = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout_s:.0f} s"
    if res.returncode == 0:
        return None
    lines = [ln for ln in (res.stderr or res.stdout).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else f"exit status {res.returncode}"


def select_gl_backend(requested: str = "auto") -> str:
    """The GL backend this process renders with, chosen (and set in ``MUJOCO_GL``) if still open.

    ``requested``: ``auto`` (keep ``MUJOCO_GL`` if set, else the first of egl, osmesa that
    works), ``egl`` or ``osmesa``. Once mujoco is imported the backend is fixed: asking for
    another one raises a ``RuntimeError`` saying to set ``MUJOCO_GL`` before start-up.
    """
    if requested not in ("auto",) + GL_BACKENDS:
        raise ValueError(f"render backend {requested!r} is not a GL backend; expected auto, egl or osmesa")
    current = os.environ.get("MUJOCO_GL")
    if "mujoco" in sys.modules:
        if current not in GL_BACKENDS:
            raise RuntimeError(
                f"mujoco was imported with MUJOCO_GL={current!r}; headless rendering needs MUJOCO_GL=egl or "
                "osmesa set before mujoco is imported (e.g. export MUJOCO_GL=egl)"
            )
        if requested != "auto" and requested != current:
            raise RuntimeError(
                f"render backend {requested!r} was requested but this process renders with MUJOCO_GL={current!r}; "
                f"set MUJOCO_GL={requested} before starting"
            )
        return current
    candidates = [requested] if requested != "auto" else ([current] if current in GL_BACKENDS else list(GL_BACKENDS))
    errors = {}
    for name in candidates:
        err = probe_gl_backend(name)
        if err is None:
            os.environ["MUJOCO_GL"] = name
            os.environ["PYOPENGL_PLATFORM"] = name
            return name
        errors[name] = err
    detail = "; ".join(f"{k}: {v}" for k, v in errors.items())
    raise RuntimeError(
        f"no working MuJoCo GL backend ({detail}). Install libegl1 + libegl-mesa0 (egl) or libosmesa6 (osmesa), "
        "or use the numpy renderer (env.render_backend=numpy)"
    )


def _hidden_model(model: Any, robot_bodies: set[int], table_geoms: set[int]) -> Any:
    """A copy of ``model`` drawn without the robot, textures, specular light or shadows."""
    m = copy.deepcopy(model)
    hidden = subtree_bodies(m, robot_bodies)
    for i in range(m.ngeom):
        if int(m.geom_bodyid[i]) in hidden:
            m.geom_group[i] = 5
    for i in range(m.nsite):
        if int(m.site_bodyid[i]) in hidden:
            m.site_group[i] = 5
    m.mat_texid[:] = -1
    m.mat_specular[:] = 0.0
    m.mat_reflectance[:] = 0.0
    m.light_specular[:] = 0.0
    m.light_castshadow[:] = 0
    m.vis.headlight.specular[:] = 0.0
    m.vis.quality.offsamples = 0
    for i in table_geoms:
        m.geom_matid[i] = -1
        m.geom_rgba[i] = np.append(TABLE_COLOR / 255.0, 1.0)
    return m


class GLTopDownRenderer:
    """MuJoCo's GL renderer looking straight down (orthographic) at ``view``, robot hidden.

    Same view, same geometry as :class:`~covers_dist.envs.topdown_render.TopDownRasterizer`;
    used as an observation backend (``egl``/``osmesa``) and to check the rasterizer.
    """

    def __init__(
        self,
        model: Any,
        data: Any,
        view: TopDownView,
        robot_bodies: set[int] | frozenset[int],
        table_geoms: set[int] | frozenset[int] = frozenset(),
        backend: str = "auto",
    ) -> None:
        select_gl_backend(backend)
        import mujoco

        self._mujoco = mujoco
        self.data, self.view = data, view
        self.model = _hidden_model(model, set(robot_bodies), set(table_geoms))
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, view.size)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, view.size)
        self._renderer = mujoco.Renderer(self.model, view.size, view.size)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = (view.centre[0], view.centre[1], 0.0)
        # MuJoCo's free camera is orthographic when the model says so; fovy is then the visible height
        self.model.vis.global_.orthographic = 1
        self.model.vis.global_.fovy = 2.0 * view.half_width
        self.camera.distance = 1.5
        self.camera.azimuth, self.camera.elevation = 90.0, -90.0  # x right, y up in the image
        self.option = mujoco.MjvOption()
        self.option.geomgroup[3:] = 0
        self.option.sitegroup[3:] = 0
        for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX", "mjRND_FOG", "mjRND_HAZE"):
            self._renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = 0

    def render(self, disc_xy: np.ndarray | None = None, disc_radius: float = 0.03) -> np.ndarray:
        """Colour image (S, S, 3) uint8, with the gripper disc if ``disc_xy`` is given."""
        self._renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        img = self._renderer.render().copy()
        if disc_xy is not None:
            draw_disc(img, self.view.to_pixels(np.asarray(disc_xy)[:2]), disc_radius / self.view.pitch)
        return img

    def segmentation(self) -> np.ndarray:
        """Per pixel: geom id, ``-2 - site id`` for sites, -1 where nothing is seen."""
        self._renderer.enable_segmentation_rendering()
        try:
            self._renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
            seg = self._renderer.render()
        finally:
            self._renderer.disable_segmentation_rendering()
        ids, types = seg[..., 0], seg[..., 1]
        out = np.full(ids.shape, -1, dtype=np.int32)
        geom = types == int(self._mujoco.mjtObj.mjOBJ_GEOM)
        site = types == int(self._mujoco.mjtObj.mjOBJ_SITE)
        out[geom] = ids[geom]
        out[site] = -2 - ids[site]
        return out

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class StockTopViewRenderer:
    """Meta-World's own ``topview`` camera (arm drawn) with fast GL settings.

    Shadows, reflections, skybox and multisampling off; the reference point for the rendering
    benchmark.
    """

    def __init__(self, model: Any, data: Any, size: int, backend: str = "auto", camera: str = "topview") -> None:
        select_gl_backend(backend)
        import mujoco

        self.data, self.camera = data, camera
        self.model = copy.deepcopy(model)
        self.model.vis.quality.offsamples = 0
        self._renderer = mujoco.Renderer(self.model, size, size)
        for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX"):
            self._renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = 0

    def render(self) -> np.ndarray:
        self._renderer.update_scene(self.data, camera=self.camera)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
