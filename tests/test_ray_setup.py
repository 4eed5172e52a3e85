"""A local Ray instance that covers-dist starts is shut down with its temp dir removed; after a
failure the dir stays, with Ray's logs. (The clean path on a real run: tests/test_bench_learn.py's
peer test, whose RLlib peer leaves no ``covers-ray-*`` dir behind.)"""

import json
import os
import subprocess
import sys
from pathlib import Path

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
