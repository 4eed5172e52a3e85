"""A serial episode collector: run a policy on a few gymnasium envs in lockstep, in one process.

It produces episodes in the format of docs/guide/architecture.md (the distributed rollout workers
produce the same), batching the policy's inference over the envs that are still running. It is
what the learning tests and the learner benchmark use; the runtime has its own workers.

Episode success is ``max(success)`` over the steps (Meta-World's convention: the goal was reached
at some point).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from .noise import NoiseSequences

__all__ = ["collect_episodes", "run_lockstep", "success_rate"]


def collect_episodes(
    model: Any,
    envs: Sequence[Any],
    num_episodes: int,
    seed: int,
    generator: torch.Generator | None = None,
    deterministic: bool = False,
) -> list[dict[str, Any]]:
    """Run ``num_episodes`` episodes spread over ``envs`` (round-robin waves) with ``model.act``.

    Episode ``i`` resets its env with seed ``seed + i``, so a seed fixes the task instances;
    ``generator`` fixes the sampled actions. Episodes come back in index order.
    """
    if num_episodes < 1 or not envs:
        raise ValueError(f"need num_episodes >= 1 and at least one env, got {num_episodes} and {len(envs)} envs")
    episodes: list[dict[str, Any]] = []
    for wave in range(0, num_episodes, len(envs)):
        active = envs[: min(len(envs), num_episodes - wave)]
        seeds = [seed + wave + i for i in range(len(active))]
        wave_episodes = run_lockstep(model, active, seeds, generator, deterministic)
        for i, ep in enumerate(wave_episodes):
            ep["episode_index"] = wave + i
        episodes.extend(wave_episodes)
    return episodes


def run_lockstep(
    model: Any,
    envs: Sequence[Any],
    seeds: Sequence[int],
    generator: torch.Generator | None = None,
    deterministic: bool = False,
    noise_beta: float | Sequence[float] = 0.0,
    noise_steps: int = 100,
    noise_coloured: Sequence[bool] | None = None,
) -> list[dict[str, Any]]:
    """One full episode per env, stepped together (one batched ``model.act`` per step).

    Env ``i`` is reset with ``seeds[i]``. Returns Episode dicts (with ``task`` and ``g`` read from
    the envs); the rollout workers of the runtime add their own metadata. ``noise_beta > 0``
    samples with coloured noise (:mod:`covers_dist.ppo.noise`): one sequence of ``noise_steps``
    steps per env, drawn from ``generator`` at the start (0: white noise drawn per step by the model);
    a sequence gives each env its own colour; ``noise_coloured`` (one flag per action entry,
    :func:`covers_dist.ppo.noise.coloured_entries`) keeps the unflagged entries white.
    """
    n = len(envs)
    if len(seeds) != n:
        raise ValueError(f"need one seed per env, got {len(seeds)} seeds for {n} envs")
    coloured = None
    betas = list(noise_beta) if isinstance(noise_beta, Sequence) else [noise_beta] * n
    if len(betas) != n:
        raise ValueError(f"need one noise_beta per env, got {len(betas)} for {n} envs")
    if any(b > 0.0 for b in betas) and not deterministic:
        coloured = NoiseSequences(betas, noise_steps, envs[0].action_space.shape[0], n, generator, noise_coloured)
    obs = [env.reset(seed=int(s))[0] for env, s in zip(envs, seeds)]
    logs: list[dict[str, list]] = [
        {"image": [o["image"]], "proprio": [o["proprio"]], "action": [], "logprob": [], "value": [], "reward": [],
         "success": []}
        for o in obs
    ]  # fmt: skip
    done = [False] * n
    ends = [(False, False)] * n
    while not all(done):
        live = [i for i in range(n) if not done[i]]
        batch = {
            "image": np.stack([obs[i]["image"] for i in live]),
            "proprio": np.stack([obs[i]["proprio"] for i in live]),
        }
        if coloured is None:
            actions, logps, values = model.act(batch, deterministic=deterministic, generator=generator)
        else:
            noise = torch.stack([coloured.take(i, len(logs[i]["action"])) for i in live])
            actions, logps, values = model.act(batch, generator=generator, noise=noise)
        for j, i in enumerate(live):
            o, r, term, trunc, info = envs[i].step(actions[j])
            log = logs[i]
            log["action"].append(actions[j])
            log["logprob"].append(logps[j])
            log["value"].append(values[j])
            log["reward"].append(r)
            log["success"].append(float(info.get("success", 0.0)))
            log["image"].append(o["image"])
            log["proprio"].append(o["proprio"])
            obs[i] = o
            if term or trunc:
                done[i], ends[i] = True, (bool(term), bool(trunc))
    # the value of each final observation (bootstraps truncations)
    last = model.act(
        {"image": np.stack([o["image"] for o in obs]), "proprio": np.stack([o["proprio"] for o in obs])},
        deterministic=True,
    )[2]
    episodes = []
    for i, env in enumerate(envs):
        log = logs[i]
        episodes.append(
            {
                "image": np.stack(log["image"]).astype(np.uint8),
                "proprio": np.stack(log["proprio"]).astype(np.float32),
                "action": np.stack(log["action"]).astype(np.float32),
                "logprob": np.asarray(log["logprob"], np.float32),
                "value": np.append(np.asarray(log["value"], np.float32), np.float32(last[i])),
                "reward": np.asarray(log["reward"], np.float32),
                "success": np.asarray(log["success"], np.float32),
                "terminated": ends[i][0],
                "truncated": ends[i][1],
                "task": getattr(env, "task", None),
                "g": getattr(getattr(env, "g", None), "name", None),
            }
        )
    return episodes


def success_rate(episodes: Sequence[dict[str, Any]]) -> float:
    """Fraction of episodes with success at some step."""
    if not episodes:
        raise ValueError("success_rate needs at least one episode")
    return float(np.mean([float(np.max(ep["success"])) > 0 for ep in episodes]))
