"""The smoke config end to end on Ray (2 CPUs): one policy per toy group, and learning."""

import json

import numpy as np

from covers_dist.config import load_config
from covers_dist.runtime.driver import Trainer


def test_smoke_stream_clusters_by_group_and_improves(ray_local, tmp_path):
    cfg = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path}", "runtime.log_every_s=15"])
    trainer = Trainer(cfg)
    result = trainer.run()
    trainer.close()
    assert result["status"] == "finished"
    assert result["num_policies"] == 3, result["policy_counts"]
    assert result["ari"] >= 0.9
    episodes = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert len(episodes) == cfg.runtime.total_env_steps // cfg.env.max_episode_steps
    gains = {}
    for task in cfg.env.tasks:
        success = np.array([e["success"] for e in episodes if e["task"] == task])
        third = len(success) // 3
        gains[task] = (success[:third].mean(), success[-third:].mean())
    print("success first third -> last third:", gains)
    assert any(late >= early + 0.15 for early, late in gains.values()), gains
