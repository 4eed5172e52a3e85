"""A local Ray instance started by covers-dist leaves nothing behind in the temp directory, unless
its logs are kept (as after a failed run)."""

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

SCRIPT = """
import json, os
import covers_dist.runtime.ray_setup as setup
from covers_dist.runtime.ray_setup import init_ray, shutdown_ray
out = {}
for keep in (False, True):
    init_ray(num_cpus=1)
    temp = setup._TEMP_DIR
    logs = os.path.isdir(os.path.join(temp, "session_latest", "logs"))
    kept = shutdown_ray(keep_logs=keep)
    out[str(keep)] = {"temp": temp, "logs_while_running": logs, "returned": kept, "exists": os.path.isdir(temp)}
print(json.dumps(out))
"""


def test_shutdown_removes_the_instances_temp_dir_unless_its_logs_are_kept():
    base = tempfile.mkdtemp(prefix="crs-", dir="/tmp" if os.path.isdir("/tmp") else None)  # short: Ray's socket paths
    env = {**os.environ, "TMPDIR": base, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    env.pop("RAY_ADDRESS", None)
    try:
        done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-4000:]
        out = json.loads(done.stdout.strip().splitlines()[-1])
        clean, kept = out["False"], out["True"]
        assert clean["temp"].startswith(base) and clean["logs_while_running"]
        assert clean["returned"] is None and not clean["exists"]
        assert kept["returned"] == kept["temp"] and kept["exists"]
        assert (Path(kept["temp"]) / "session_latest" / "logs").is_dir()
        assert sorted(p.name for p in Path(base).iterdir()) == [Path(kept["temp"]).name]
    finally:
        shutil.rmtree(base, ignore_errors=True)
