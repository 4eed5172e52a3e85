"""Shared test set-up: headless rendering and loopback-only Ray, set before anything imports them."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
