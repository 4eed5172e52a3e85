"""The clustering benchmarks: ``bench ablate``, ``bench assign --stream`` settings, ``bench features``."""

from __future__ import annotations

import argparse
import json

import pytest

from covers_dist.bench import ablate
from covers_dist.bench._assign_stream import settings
from covers_dist.cli import main
from covers_dist.config import load_config


def test_ablate_cells_are_the_papers_grid_and_bad_names_are_refused():
    assert ablate.cells_of("metric") == [f"{m}@{t}" for m, ts in (
        ("wasserstein", (0.6, 1.0, 1.4)), ("euclidean", (0.5, 0.8, 1.1)), ("mahalanobis", (5.0, 10.0, 15.0))
    ) for t in ts]  # fmt: skip
    assert ablate.cells_of("buffer") == [f"buffer={n}" for n in (32, 64, 128, 256, 512)]
    assert ablate.cells_of("default,buffer=64,buffer") [:2] == ["default", "buffer=64"]
    assert len(ablate.cells_of("default,buffer=64,buffer")) == 6  # no repeats
    for cell, overrides in ablate.CELLS.items():  # every cell is a valid config
        cfg = load_config("stream_fast", overrides)
        if cell.startswith("buffer="):
            assert cfg.clustering.buffer_size == int(cell.split("=")[1])
        elif cell != "default":
            assert cfg.clustering.rule == "threshold" and cfg.clustering.metric == cell.split("@")[0]
    with pytest.raises(SystemExit, match="unknown cell 'w1'"):
        ablate.cells_of("w1")
    with pytest.raises(SystemExit, match="no cell"):
        ablate.cells_of(" , ")
    with pytest.raises(SystemExit, match="--seeds must be comma-separated integers"):
        main(["bench", "ablate", "--seeds", "a"])
    with pytest.raises(SystemExit, match="--stream must be metaworld-multi or metaworld-mono"):
        main(["bench", "ablate", "--stream", "toy-one"])


def test_ablate_runs_a_cell_with_training_encoders(capsys):
    capsys.readouterr()
    assert main(["bench", "ablate", "--cells", "buffer=32", "--seeds", "0", "--steps", "1200", "--json"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    run, cell = lines
    assert run["cell"] == "buffer=32" and run["env_steps"] == 1200 and run["feature_source"] == "joint"
    assert run["policies_created"] >= run["policies"] >= 1 and run["false_splits"] >= 0 and 0 <= run["ari"] <= 1
    assert cell["cell"] == "buffer=32" and cell["seeds"] == [0] and cell["ari"] == run["ari"]


def test_assign_stream_takes_rule_moment_and_batch_from_a_given_config():
    ns = argparse.Namespace(config="stream_fast", overrides=[], rules=None, assign_at=None, steps=0, batch=0)
    rules, modes, steps, batch = settings("metaworld-mono", ns)
    assert (rules, modes, batch) == (["calibrated"], ["reset"], 8) and steps == 16 * 32 * 150
    ns = argparse.Namespace(config=None, overrides=[], rules=None, assign_at=None, steps=0, batch=0)
    assert settings("toy-one", ns) == (["threshold", "calibrated"], ["iteration", "reset"], 8000, 4)
    with pytest.raises(SystemExit, match="unknown or empty stream"):
        main(["bench", "assign", "--stream", "--streams", "metaworld-pink"])


def test_bench_features_measures_every_candidate_on_a_saved_run(tmp_path, capsys):
    from covers_dist.runtime.driver import Trainer

    cfg = load_config(
        "smoke",
        [f"runtime.run_dir={tmp_path / 'run'}", "runtime.total_env_steps=400", "runtime.serial=true",
         "runtime.num_workers=1", "runtime.checkpoint_every=100", "eval.every_iterations=0"],
    )  # fmt: skip
    trainer = Trainer(cfg, log=lambda *_: None)
    assert trainer.run()["status"] == "finished"
    trainer.close()
    capsys.readouterr()
    assert main(["bench", "features", str(tmp_path / "run"), "--batch", "2", "--batches", "2", "--json"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [r["candidate"] for r in rows] == ["own", "joint", "fresh", "colors"]
    for r in rows:
        assert r["policies"] >= 1 and abs(r["correct"] + r["new"] + r["wrong"] - 1.0) < 1e-9
        assert r["batches"] == 2 * len(cfg.env.tasks)
    with pytest.raises(SystemExit, match="unknown candidate"):
        main(["bench", "features", str(tmp_path / "run"), "--candidates", "hist"])
    with pytest.raises(SystemExit, match="neither a checkpoint nor a run directory"):
        main(["bench", "features", str(tmp_path / "nothing")])
