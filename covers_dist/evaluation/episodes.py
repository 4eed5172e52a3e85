"""The evaluation episode loop: every evaluation of the project rolls its episodes here.

``covers-dist eval``, the periodic passes during training (both through the rollout workers'
``eval_jobs``) and ``covers-dist bench learn`` (covers-dist and its peers alike) run
:func:`run_eval_episodes`: one episode per (env, seed), the envs stepped in lockstep with one
batched ``policy.act`` per step. A *policy* is anything with
``act(obs, deterministic=..., generator=...)`` returning the actions first (a covers-dist
:class:`~covers_dist.models.ActorCritic` is one); a framework's greedy policy (RLlib's RLModule,
Stable-Baselines3's model) plugs in through :class:`GreedyPolicy`.

Each episode reports its success (``info["success"]`` ever true, Meta-World's convention), its
return and a fingerprint of its initial state (:func:`initial_state_key`): the first observation
mapped back to the base task by ``g^-1``, so the same underlying state has the same key under
every element and two keys differ only where the states do. Where the env reports how far the
task is from success (``info["target_ratio"]``, Meta-World's ``obj_to_target`` over the success
radius), the episode also reports its ``closest`` approach: a failure at 1.1 stopped just outside
the radius, one at 5 never came near. Plain Python and numpy; torch only for the sampling
generator of stochastic episodes.
"""

from __future__ import annotations

import hashlib
from typing import Any, Callable, Mapping, Sequence

import numpy as np

__all__ = ["GreedyPolicy", "run_eval_episodes", "initial_state_key"]

#: Decimals the proprio vector is rounded to in a fingerprint (float32 noise does not split states).
_KEY_DECIMALS = 5


class GreedyPolicy:
    """A greedy-only policy (``act_fn(obs) -> actions``) in the shape the loop calls.

    ``act_fn`` takes a batch ``{"image": uint8 (B, S, S, 3), "proprio": (B, P)}`` and returns the
    actions (B, A). Asking it for sampled actions raises ``ValueError`` (an adapter that cannot
    sample must not be scored as if it did).
    """

    def __init__(self, act_fn: Callable[[Mapping[str, np.ndarray]], np.ndarray], name: str = "greedy") -> None:
        self.act_fn = act_fn
        self.name = name

    def act(self, obs: Mapping[str, np.ndarray], deterministic: bool = True, generator: Any = None) -> tuple:
        if not deterministic:
            raise ValueError(f"policy {self.name!r} acts greedily only; evaluate it with mode 'greedy'")
        actions = np.asarray(self.act_fn(obs), dtype=np.float32)
        return actions, None, None


def initial_state_key(obs: Mapping[str, np.ndarray], g: Any, layout: Any | None = None) -> str:
    """A fingerprint of an episode's initial state, the same for ``g.T`` and ``T`` in the same state.

    The first observation is mapped back by ``g^-1`` (image pixels exactly; proprio by ``layout``'s
    planar pairs, rounded) and hashed. ``g`` is a :class:`~covers_dist.symmetry.GroupElement`.
    """
    inv = g.inverse()
    image = inv.apply_image(np.asarray(obs["image"]))
    proprio = np.asarray(obs["proprio"], dtype=np.float64)
    if layout is not None:
        proprio = layout.transform_proprio(inv, proprio)
    proprio = np.round(proprio, _KEY_DECIMALS) + 0.0  # + 0.0: -0.0 and 0.0 hash alike
    digest = hashlib.sha1(np.ascontiguousarray(image).tobytes())
    digest.update(np.ascontiguousarray(proprio).tobytes())
    return digest.hexdigest()[:16]


def run_eval_episodes(
    policy: Any,
    envs: Sequence[Any],
    seeds: Sequence[int],
    deterministic: bool = True,
    generator: Any = None,
    layout: Any | None = None,
) -> list[dict[str, Any]]:
    """One episode per env, env ``i`` reset with ``seeds[i]``; per episode ``{"success", "return",
    "length", "state_key", "closest"}`` (``state_key`` only when the envs expose their element ``g``;
    ``closest``, the episode's smallest ``info["target_ratio"]``, only when the env reports one)."""
    n = len(envs)
    if len(seeds) != n:
        raise ValueError(f"need one seed per env, got {len(seeds)} seeds for {n} envs")
    obs = [env.reset(seed=int(s))[0] for env, s in zip(envs, seeds)]
    keys = [
        initial_state_key(o, env.g, layout) if getattr(env, "g", None) is not None else None
        for env, o in zip(envs, obs)
    ]
    success = [0.0] * n
    returns = [0.0] * n
    lengths = [0] * n
    closest: list[float | None] = [None] * n
    live = list(range(n))
    while live:
        batch = {"image": np.stack([obs[i]["image"] for i in live]), "proprio": np.stack([obs[i]["proprio"] for i in live])}
        actions = policy.act(batch, deterministic=deterministic, generator=generator)[0]
        still = []
        for j, i in enumerate(live):
            obs[i], reward, terminated, truncated, info = envs[i].step(actions[j])
            success[i] = max(success[i], float(info.get("success", 0.0)))
            if "target_ratio" in info:
                ratio = float(info["target_ratio"])
                closest[i] = ratio if closest[i] is None else min(closest[i], ratio)
            returns[i] += float(reward)
            lengths[i] += 1
            if not (terminated or truncated):
                still.append(i)
        live = still
    return [
        {
            "success": success[i],
            "return": returns[i],
            "length": lengths[i],
            **({"state_key": keys[i]} if keys[i] else {}),
            **({"closest": closest[i]} if closest[i] is not None else {}),
        }
        for i in range(n)
    ]
