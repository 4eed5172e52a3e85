"""Learning: one equivariant policy trained with this PPO on one toy task transfers zero-shot to the
task's rotated and mirrored copies; the CNN twin, trained the same way, does not."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
import torch

from covers_dist.config import NetworkConfig, PPOConfig
from covers_dist.envs.toy import ToyTask, toy_layout
from covers_dist.models import build_actor_critic
from covers_dist.ppo import PPOLearner, collect_episodes, success_rate
from covers_dist.symmetry import D4_ELEMENTS

TASK = "reach"
IMAGE_SIZE = 32
NUM_ENVS = 8
EPISODES_PER_UPDATE = 16
SUCCESS_THRESHOLD = 0.8
EVAL_EPISODES = 16
EPISODE_STEPS = 25  # reaching takes about 8 steps; shorter episodes keep the test cheap
NET = NetworkConfig(channels=[2, 4, 8, 16], hidden=32)  # narrow: cheap enough for the default suite
PPO = dataclasses.replace(PPOConfig(), lr=1e-3)  # defaults otherwise (reward_scale 0.1, 4 epochs, ...)



def train(kind: str, max_updates: int, seed: int = 0):
    """PPO on the untransformed task until three updates in a row succeed >= 0.9 (or the budget ends)."""
    model = build_actor_critic(NET, toy_layout(IMAGE_SIZE), kind=kind, seed=seed)
    learner = PPOLearner(model, PPO, seed=seed)
    envs = [ToyTask(TASK, "e", image_size=IMAGE_SIZE, max_episode_steps=EPISODE_STEPS) for _ in range(NUM_ENVS)]
    generator = torch.Generator().manual_seed(seed)
    streak, history = 0, []
    for update in range(max_updates):
        episodes = collect_episodes(model, envs, EPISODES_PER_UPDATE, seed=1000 * (update + 1), generator=generator)
        stats = learner.update(episodes)
        history.append(stats["success_rate"])
        streak = streak + 1 if stats["success_rate"] >= 0.9 else 0
        print(f"{kind} update {update}: success {stats['success_rate']:.2f} return {stats['episode_return_mean']:.1f}")
        if streak >= 3:
            break
    return model, history


def evaluate(model, deterministic: bool, seed: int = 10**6) -> dict[str, float]:
    """Success on the task's copy g.T for every g (the same task instances for every g)."""
    rates = {}
    for g in D4_ELEMENTS:
        envs = [ToyTask(TASK, g, image_size=IMAGE_SIZE, max_episode_steps=EPISODE_STEPS) for _ in range(NUM_ENVS)]
        generator = torch.Generator().manual_seed(seed)
        episodes = collect_episodes(
            model, envs, EVAL_EPISODES, seed=seed, generator=generator, deterministic=deterministic
        )
        rates[g.name] = success_rate(episodes)
    return rates


def test_equivariant_policy_learns_the_toy_task_and_scores_alike_on_every_copy(one_torch_thread):
    """The default suite's learning assertion: PPO trains the equivariant policy on the untransformed
    copy until three updates in a row succeed >= 0.9, and its greedy policy then scores exactly
    alike on every rotated and mirrored copy (the same task instances on each). The CNN twin's
    comparison, which doubles the cost, is the slow test below."""
    equi, history = train("equivariant", max_updates=40)
    assert len(history) < 40 and min(history[-3:]) >= 0.9, history  # learned within the budget
    greedy = evaluate(equi, deterministic=True)
    assert len(set(greedy.values())) == 1, greedy


@pytest.mark.slow
def test_equivariant_policy_transfers_zero_shot_and_cnn_twin_does_not(one_torch_thread):
    """Slow tier (1-2 minutes on 2 cores: two networks trained to a threshold, four evaluations).
    The default suite trains the equivariant policy alone (above) and checks the networks'
    equivariance exactly (tests/test_models.py)."""
    start = time.perf_counter()
    equi, equi_history = train("equivariant", max_updates=40)
    # as many updates as the equivariant net took, with the same stopping rule (on 2 cores the CNN
    # twin's success on the trained copy levels off at about 0.5 from its 4th update on)
    cnn, cnn_history = train("cnn", max_updates=len(equi_history))
    equi_greedy, equi_sampled = evaluate(equi, deterministic=True), evaluate(equi, deterministic=False)
    cnn_sampled, cnn_greedy = evaluate(cnn, deterministic=False), evaluate(cnn, deterministic=True)
    print(
        f"equivariant greedy: {equi_greedy}\nequivariant sampled: {equi_sampled}\ncnn sampled: {cnn_sampled}\ncnn greedy: {cnn_greedy}\n"
        f"updates: {len(equi_history)}; {time.perf_counter() - start:.0f} s"
    )
    # the equivariant policy solves the trained copy (sampled or greedy: which mode is better on
    # this toy task changes with the run) ...
    assert max(equi_greedy["e"], equi_sampled["e"]) >= SUCCESS_THRESHOLD, (equi_history, equi_greedy, equi_sampled)
    assert np.mean(list(equi_sampled.values())) >= SUCCESS_THRESHOLD - 0.2, equi_sampled  # on every copy too
    # ... and, zero-shot, every rotated / mirrored copy exactly as well (closed-loop equivariance)
    assert len(set(equi_greedy.values())) == 1, equi_greedy
    # the CNN twin learned the trained copy too: its training success levels off at 0.4-0.5, and
    # its rate on "e" over 16 evaluation episodes depends on the CPU's float kernels (>= 0.4 on an
    # Intel Xeon, 0.25 greedy / 0.31 sampled on an AMD EPYC with AVX-512), ...
    assert np.mean(cnn_history[-10:]) >= 0.3, cnn_history
    assert max(cnn_sampled["e"], cnn_greedy["e"]) >= 0.2, (cnn_sampled, cnn_greedy)
    # ... but does not transfer
    for rates in (cnn_sampled, cnn_greedy):
        transformed = [rate for g, rate in rates.items() if g != "e"]
        assert np.mean(transformed) <= 0.3, rates
        assert np.mean(transformed) <= equi_greedy["r"] - 0.5, rates
