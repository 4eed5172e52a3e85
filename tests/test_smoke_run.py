"""The smoke config end to end: one policy per toy group, and learning.

The default suite runs one round of the three groups and the first iteration of the next round,
in one process (``runtime.serial``: the clustering decisions are under test, and a Ray run of the
same config makes the same ones, tests/test_chaos.py) with one PPO epoch: every group gets its own
policy, and the group that comes back is recalled (not given a new policy). The full config's run
on Ray (2 CPUs), where the reach group's success rises, is marked slow; that this PPO learns a toy
task is the default suite's tests/test_learning.py."""

import json

import numpy as np
import pytest

from covers_dist.config import load_config
from covers_dist.runtime.driver import Trainer


def _run(tmp_path, *overrides):
    cfg = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path}", "runtime.log_every_s=15", *overrides])
    trainer = Trainer(cfg)
    try:
        result = trainer.run()
        records = trainer.backend.call_clustering("assignments", 0, 10**6)
    finally:
        trainer.close()
    assert result["status"] == "finished"
    assert result["num_policies"] == 3, result["policy_counts"]
    assert result["ari"] >= 0.9
    episodes = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert len(episodes) == cfg.runtime.total_env_steps // cfg.env.max_episode_steps
    return cfg, records, episodes


def test_one_round_gives_each_group_a_policy_and_recalls_a_returning_group(tmp_path):
    base = load_config("configs/smoke.yaml")
    per_iteration = base.clustering.update_every * base.env.max_episode_steps
    one_round = len(base.env.tasks) * base.env.episodes_per_task * base.env.max_episode_steps
    # the clustering decisions are what is checked, not learning: one epoch, in one process. The
    # config's own network and image size: with a narrower one (channels [2,4], 8 hidden units, 16 px)
    # the avoid and push groups' initial frames lie at W1 0.9-1.0 of each other's buffers, at the
    # threshold (1.0), and whether they split depended on the seed and the CPU's arithmetic; at these
    # sizes, 7 runs on Ray (4 seeds) split all three, other groups at >= 1.3 and the same group <= 0.73;
    # in one process at seed 0 (this test), other groups at >= 1.19 and the same group <= 0.71, alike
    # with fp32 and bf16 learners
    cfg, records, episodes = _run(tmp_path, f"runtime.total_env_steps={one_round + per_iteration}", "ppo.epochs=1",
                                  "runtime.serial=true")  # fmt: skip
    assert sorted({e["task"] for e in episodes[: one_round // cfg.env.max_episode_steps]}) == sorted(cfg.env.tasks)
    decisions = [r["decision"] for r in records]
    last = records[-1]
    # the next round's first group was seen in the first round: its policy is recalled, no new one
    assert last["decision"] == "recall", decisions
    returning = episodes[-1]["task"]
    first_policy = next(e["assigned_policy"] for e in episodes if e["task"] == returning)
    assert last["policy_id"] == first_policy, (returning, records)
    # the real log's one re-entry: the returning group's last iteration of round one -> its first of round two
    from covers_dist.evaluation.reentry import reentry_changes

    w = base.clustering.update_every
    gaps = reentry_changes(episodes, window=w)
    assert list(gaps) == [returning] and gaps[returning]["reentries"] == 1
    first_segment = [e for e in episodes[: one_round // cfg.env.max_episode_steps] if e["task"] == returning]
    assert gaps[returning]["return_before"] == pytest.approx(np.mean([e["return"] for e in first_segment[-w:]]))
    assert gaps[returning]["return_after"] == pytest.approx(np.mean([e["return"] for e in episodes[-w:]]))


@pytest.mark.slow
def test_smoke_stream_clusters_by_group_and_improves(ray_local, tmp_path):
    """The whole smoke config (10 rounds, about 4 min on 2 cores)."""
    cfg, _, episodes = _run(tmp_path)
    gains = {}
    for task in cfg.env.tasks:
        success = np.array([e["success"] for e in episodes if e["task"] == task])
        third = len(success) // 3
        gains[task] = (success[:third].mean(), success[-third:].mean())
    print("success first third -> last third:", gains)
    assert any(late >= early + 0.15 for early, late in gains.values()), gains
