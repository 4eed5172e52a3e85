"""Every ``covers-dist`` command from a plain shell: no MUJOCO_GL, PYOPENGL_PLATFORM or RAY_*
variable, PATH=/usr/bin:/bin, a fresh HOME. The console script's ``--help`` and real short runs of
the commands that render, train or serve cheaply; each subcommand's ``--help`` in this process."""

import argparse
import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from covers_dist.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).parent / "covers-dist")
SMOKE = str(ROOT / "configs" / "smoke.yaml")
TINY_TRAIN = ["--set", "runtime.total_env_steps=400", "--set", "runtime.log_every_s=1000", "--set", "network.channels=[2,4]",
              "--set", "network.hidden=8"]


def _subcommands() -> list[list[str]]:
    def subparsers(parser):
        return next((a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {})

    out = []
    for name, parser in subparsers(build_parser()).items():
        out.append([name])
        out += [[name, sub] for sub in subparsers(parser)]
    return out


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """``run(*ARGS)``: ``covers-dist ARGS`` in a clean environment (``module=True``: ``python -m
    covers_dist ARGS``); returns the CompletedProcess."""
    base = tmp_path_factory.mktemp("plain")
    (base / "home").mkdir()
    (base / "tmp").mkdir()
    clean = {"PATH": "/usr/bin:/bin", "HOME": str(base / "home"), "TMPDIR": str(base / "tmp")}

    def run(*args, timeout=120, env=None, cwd=base, module=False):
        exe = [sys.executable, "-m", "covers_dist"] if module else [EXE]
        res = subprocess.run([*exe, *map(str, args)], env={**clean, **(env or {})}, cwd=cwd, capture_output=True,
                             text=True, timeout=timeout)
        assert "MUJOCO_GL=None" not in res.stderr
        return res

    run.env, run.base = clean, base
    return run


def test_every_subcommand_is_discovered():
    names = {" ".join(c) for c in _subcommands()}
    assert {"config", "train", "plot", "eval", "report", "serve", "demo", "bench", "bench render", "bench toy"} <= names


@pytest.mark.parametrize("command", _subcommands(), ids=" ".join)
def test_help(command, capsys):
    """Every subcommand's --help, in this process (the CLI's main, as the console script calls it)."""
    with pytest.raises(SystemExit) as exc:
        main([*command, "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: covers-dist {' '.join(command)}")


def test_the_console_script_starts_in_a_plain_shell(plain):
    """The installed console script, not the CLI's main in this process: it starts, discovers every
    subcommand and prints its help (the commands below run it with real work)."""
    res = plain("--help", timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("usage: covers-dist")
    assert all(c[0] in res.stdout for c in _subcommands())


def test_bench_render_draws_meta_world_with_gl(plain):
    res = plain("bench", "render", "--tasks", "reach-v3", "--image-size", "32", "--steps", "5", "--stock-steps", "5",
                "--repeats", "1", "--policy", "random", "--agreement", "--json")
    assert res.returncode == 0, res.stderr
    row, agreement = (json.loads(line) for line in res.stdout.splitlines())
    assert row["task"] == "reach-v3" and row["stock_rendered_steps_per_s"] > 0 and row["rendered_steps_per_s"] > 0
    # MuJoCo's GL camera and the numpy rasterizer see the same geoms, pixel for pixel
    assert agreement["segmentation_agreement"] > 0.95


def test_python_m_covers_dist_renders_with_gl(plain):
    res = plain("bench", "render", "--tasks", "reach-v3", "--image-size", "32", "--steps", "5", "--repeats", "1",
                "--policy", "random", "--no-stock", "--backend", "egl", "--json", module=True)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["backend"] == "egl"


def test_an_explicit_mujoco_gl_is_kept(plain):
    res = plain("bench", "render", "--tasks", "reach-v3", "--image-size", "32", "--steps", "5", "--repeats", "1",
                "--policy", "random", "--no-stock", "--backend", "osmesa", "--json", env={"MUJOCO_GL": "osmesa"})
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["backend"] == "osmesa"
    # asking for the other backend names the one the user chose
    res = plain("bench", "render", "--tasks", "reach-v3", "--image-size", "32", "--steps", "5", "--repeats", "1",
                "--policy", "random", "--no-stock", "--backend", "egl", env={"MUJOCO_GL": "osmesa"})
    assert res.returncode != 0 and "MUJOCO_GL='osmesa'" in res.stderr


def test_config_demo_and_bench_toy(plain):
    res = plain("config", "--config", SMOKE, "--set", "runtime.log_rotate_mb=8")
    assert res.returncode == 0, res.stderr
    assert "log_rotate_mb: 8.0" in res.stdout and "name: smoke" in res.stdout
    res = plain("config", "--describe")
    assert res.returncode == 0 and "runtime.log_keep" in res.stdout
    res = plain("config", "--config", SMOKE, "--set", "runtime.log_rotate_mb=0")
    assert res.returncode == 2 and "runtime.log_rotate_mb=0.0 must be > 0" in res.stderr
    res = plain("demo", "--out", plain.base / "demo", "--episodes", "1", "--image-size", "32")
    assert res.returncode == 0, res.stderr
    assert (plain.base / "demo" / "toy_grid.png").is_file() and "mismatches (image or reward): 0" in res.stdout
    res = plain("bench", "toy", "--steps", "100", "--repeats", "1", "--json")
    assert res.returncode == 0, res.stderr
    assert [json.loads(line)["task"] for line in res.stdout.splitlines()] == ["reach", "push", "avoid"]


@pytest.fixture(scope="module")
def trained(plain):
    """A one-iteration serial smoke run."""
    run = plain.base / "run"
    res = plain("train", "--config", SMOKE, "--serial", "--run-dir", run, *TINY_TRAIN, timeout=240)
    assert res.returncode == 0, res.stdout + res.stderr
    assert json.loads(res.stdout.splitlines()[-1])["status"] == "finished"
    return run


def test_train_then_plot_eval_report(plain, trained):
    assert len((trained / "episodes.jsonl").read_text().splitlines()) == 16
    res = plain("plot", trained)
    assert res.returncode == 0, res.stderr
    assert (trained / "policy_timeline.png").is_file()
    res = plain("eval", trained, "--episodes", "1", "--tasks", "reach", "--modes", "greedy", "--selections", "agnostic")
    assert res.returncode == 0, res.stderr
    assert len((trained / "eval.jsonl").read_text().splitlines()) == 1
    res = plain("report", trained)
    assert res.returncode == 0, res.stderr
    assert "reach" in (trained / "report.md").read_text()


def test_serve_a_saved_run(plain, trained):
    proc = subprocess.Popen([EXE, "serve", "--run-dir", str(trained), "--port", "0"], env=plain.env,
                            cwd=plain.base, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 90
        url = None
        while url is None and time.time() < deadline:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, proc.stderr.read()
            if "listening on " in line:
                url = line.split("listening on ", 1)[1].split()[0]
        assert url is not None and url.startswith("http://127.0.0.1:")
        no_proxy = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        with no_proxy.open(f"{url}/healthz", timeout=10) as resp:
            assert json.loads(resp.read())["status"] == "ok"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    assert proc.returncode == 0


@pytest.mark.slow
def test_train_on_a_local_ray_instance(plain):
    """Ray started by the command itself, loopback-only without RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER
    (and with a TMPDIR too long for Ray's socket paths: its temp dir goes under /tmp)."""
    run = plain.base / "ray-run"
    res = plain("train", "--config", SMOKE, "--run-dir", run, *TINY_TRAIN, timeout=400)
    assert res.returncode == 0, res.stdout + res.stderr
    assert json.loads(res.stdout.splitlines()[-1])["status"] == "finished"
