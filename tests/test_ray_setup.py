"""A local Ray instance that covers-dist starts is shut down with its temp dir removed; after a
failure the dir stays, with Ray's logs. (The clean path on a real run: tests/test_bench_learn.py's
peer test, slow tier, whose RLlib peer leaves no ``covers-ray-*`` dir behind.)"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# shut down in an ``except`` block, as a ``finally`` does after a failure
SCRIPT = """
import json, os
import covers_dist.runtime.ray_setup as setup
from covers_dist.runtime.ray_setup import failing, init_ray, shutdown_ray
assert not failing()
init_ray(num_cpus=1)
temp = setup._TEMP_DIR
try:
    raise RuntimeError("a failed run")
except RuntimeError:
    kept = shutdown_ray()
print(json.dumps({"temp": temp, "kept": kept}))
"""


def test_after_a_failure_the_instances_temp_dir_stays_with_its_logs(short_tmpdir):
    env = {**os.environ, "TMPDIR": str(short_tmpdir), "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    env.pop("RAY_ADDRESS", None)
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-4000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["temp"].startswith(str(short_tmpdir)) and out["kept"] == out["temp"]
    assert (Path(out["temp"]) / "session_latest" / "logs").is_dir()


# started in a directory that holds a copy of the package: Ray's workers find that copy first
PROBE = """
import json
from covers_dist.runtime.ray_setup import init_ray, shutdown_ray
try:
    init_ray(num_cpus=1)
except RuntimeError as err:
    print(json.dumps({"error": str(err)}))
else:
    shutdown_ray()
    print(json.dumps({"error": None}))
"""


def _start_ray_beside(copy_dir, short_tmpdir):
    import covers_dist

    env = {**os.environ, "TMPDIR": str(short_tmpdir), "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    env.pop("RAY_ADDRESS", None)
    env.pop("PYTHONPATH", None)
    installed = Path(covers_dist.__file__).resolve().parent
    # the driver imports the package it was given (as a console script does), not the copy in its cwd
    code = f"import sys; sys.path[0:1] = [{str(installed.parent)!r}]\n" + PROBE
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=copy_dir, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return json.loads(done.stdout.strip().splitlines()[-1])["error"], installed


def _copy_of_the_package(root: Path) -> Path:
    import shutil

    import covers_dist

    source = Path(covers_dist.__file__).resolve().parent
    shutil.copytree(source, root / "covers_dist", ignore=shutil.ignore_patterns("__pycache__"))
    return root


@pytest.mark.slow
def test_workers_beside_the_same_sources_in_another_place_start(tmp_path, short_tmpdir):
    """The refusal below compares sources, not paths: an identical copy in the driver's working
    directory passes. Slow tier (a Ray start in its own process); the default suite's Ray starts all
    pass this check with the package's own copy."""
    error, _ = _start_ray_beside(_copy_of_the_package(tmp_path / "same"), short_tmpdir)
    assert error is None


def test_workers_importing_another_copy_of_the_package_are_refused(tmp_path, short_tmpdir):
    """Ray puts the driver's working directory first on its workers' path: a different copy of the
    package there would run every env and learner on other code. init_ray refuses it, naming both
    copies (an identical copy elsewhere passes: the slow test above)."""
    other = _copy_of_the_package(tmp_path / "other")
    with open(other / "covers_dist" / "envs" / "metaworld_suite.py", "a") as fh:
        fh.write("\n# an older or newer copy\n")
    error, installed = _start_ray_beside(other, short_tmpdir)
    assert error is not None and "their sources differ" in error
    assert str(other / "covers_dist") in error and str(installed) in error
