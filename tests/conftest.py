"""Shared test set-up: headless rendering and loopback-only Ray, set before anything imports them."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def ray_local():
    """One loopback-only Ray instance (2 CPUs) shared by every test that needs Ray."""
    from covers_dist.runtime.ray_setup import init_ray, shutdown_ray

    ray = init_ray(num_cpus=2)
    yield ray
    shutdown_ray()


@pytest.fixture(scope="module")
def one_torch_thread():
    """Small tensors on 2 shared cores: one intra-op thread is faster and reproducible."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
