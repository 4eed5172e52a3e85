"""A run directory and its storage are data, never code: a checkpoint or live state that carries a
pickled object (here one that would create a marker file when unpickled) is refused with a clear
error by every path that reads one, with a manifest that matches it, and its payload never runs."""

import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from covers_dist.cli import main
from covers_dist.clustering.persistence import file_sha256
from covers_dist.runtime.checkpoint import CheckpointError, latest_valid_checkpoint, load_state
from covers_dist.runtime.learner import PolicyLearner, live_state_key

from test_runtime_serial import tiny_cfg

REPO = Path(__file__).resolve().parents[1]


class Payload:
    """Unpickling this runs ``touch MARKER``: what a hostile file in a run directory would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def plant(path: Path, marker: Path) -> None:
    """Replace the torch file ``path`` with one that carries the payload beside real tensors."""
    torch.save({"ppo": {"model": {"w": torch.zeros(2)}}, "version": 1, "hook": Payload(marker)}, path)


def plant_in_checkpoint(run_dir: Path, marker: Path) -> Path:
    """Plant the payload in the newest checkpoint's policy 0 and rewrite its manifest to match."""
    import json

    ckpt = latest_valid_checkpoint(run_dir, log=lambda *_: None)
    target = ckpt / "learners" / "policy-0.pt"
    plant(target, marker)
    manifest = json.loads((ckpt / "manifest.json").read_text())
    manifest["files"]["learners/policy-0.pt"] = file_sha256(target)
    (ckpt / "manifest.json").write_text(json.dumps(manifest))
    assert latest_valid_checkpoint(run_dir, log=lambda *_: None) == ckpt  # the manifest vouches for it
    return ckpt


@pytest.fixture
def planted_run(tiny_serial_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_serial_run[2], run_dir)
    marker = tmp_path / "payload-ran"
    plant_in_checkpoint(run_dir, marker)
    return run_dir, marker


def test_the_payload_is_live_and_load_state_refuses_it(tmp_path):
    live = tmp_path / "live-marker"
    pickle.loads(pickle.dumps(Payload(live)))
    assert live.exists()  # the payload does run when unpickled the unsafe way
    marker = tmp_path / "marker"
    plant(tmp_path / "state.pt", marker)
    with pytest.raises(CheckpointError, match=r"state.pt is refused: it is not a torch file of tensors.*GLOBAL posix.system"):
        load_state(tmp_path / "state.pt", str(tmp_path / "state.pt"))
    with pytest.raises(CheckpointError, match="bytes is (refused: it is not a torch file|unreadable)"):
        load_state(b"not a torch file", "bytes")
    assert not marker.exists()


def refusal(argv, capsys) -> str:
    """What the command ``argv`` said when it stopped with an error (exit code 2 or a message)."""
    try:
        code = main(argv)
    except SystemExit as e:
        return str(e.code)
    assert code == 2
    return capsys.readouterr().err


def test_eval_and_resume_refuse_a_planted_checkpoint_with_a_matching_manifest(planted_run, capsys):
    run_dir, marker = planted_run
    assert "policy-0.pt is refused" in refusal(["eval", str(run_dir), "--episodes", "1"], capsys)
    assert "policy-0.pt is refused" in refusal(["train", "--resume", str(run_dir)], capsys)
    assert not marker.exists()


def test_serve_refuses_a_planted_run_directory(planted_run):
    run_dir, marker = planted_run
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, "-m", "covers_dist.cli", "serve", "--run-dir", str(run_dir), "--port", "0"],
        capture_output=True, text=True, timeout=120, env=env, cwd=REPO,
    )  # fmt: skip
    assert proc.returncode != 0, proc.stderr
    assert "policy-0.pt is refused" in proc.stderr
    assert not marker.exists()


def test_a_restarted_learner_refuses_a_planted_live_state(tmp_path):
    cfg = tiny_cfg(tmp_path / "run")
    store = tmp_path / "store"
    marker = tmp_path / "marker"
    (store / live_state_key(0)).parent.mkdir(parents=True)
    plant(store / live_state_key(0), marker)
    with pytest.raises(RuntimeError, match=r"the live state .* is refused.*--resume"):
        PolicyLearner(cfg, 0, storage=str(store))
    assert not marker.exists()
