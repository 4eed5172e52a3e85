"""A short learning run on Meta-World with the default PPO: Drawer Close under D4, serial, seeded.

What the default suite can afford (about a minute on 2 cores): the COVERS loop trains on every
rotated and mirrored copy of the task and, evaluated greedily on all 8 copies with evaluation
seeds, already succeeds on some episodes, and on every copy exactly equally (the closed loop is
equivariant). The runs that go to 0.9 are ``covers-dist bench learn`` (docs/learning.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_drawer_close_learns_from_pixels_on_every_transform_alike(tmp_path):
    cmd = [
        sys.executable, "-m", "covers_dist", "bench", "learn", "--config", "configs/quickstart.yaml",
        "--task", "drawer-close-v3", "--contenders", "covers", "--serial", "--budget-steps", "8000",
        "--eval-every", "8000", "--eval-episodes", "2", "--json", "--out", str(tmp_path),
    ]  # fmt: skip
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    curve = result["contenders"]["covers"]["curve"]
    assert [p["env_steps"] for p in curve] == [0, 8000]
    assert curve[0]["mean_success"] == 0.0  # the untrained policy never closes the drawer
    for point in curve:  # one equivariant policy: the same success on every transform
        assert len(point["success"]) == 8 and len(set(point["success"].values())) == 1, point
    assert curve[-1]["min_success"] > 0.0, done.stderr[-2000:]
