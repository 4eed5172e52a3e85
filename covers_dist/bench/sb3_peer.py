"""Stable-Baselines3's PPO on the same task stream as a covers-dist config (``bench learn``'s ``sb3``).

The PPO that users pick outside Ray: ``PPO("MultiInputPolicy")`` on the task's own dict
observation (``image`` uint8, SB3 transposes it to channels-first and scales it to [0, 1];
``proprio`` as a vector): SB3's ``CombinedExtractor`` (NatureCNN on the image, the proprio
flattened beside it), then ``net_arch`` of ``network.hidden`` units for the policy and the value
heads. The same PPO settings as every ``bench learn`` contender
(:func:`covers_dist.bench.rllib_peer.ppo_settings`): batch of one covers-dist iteration, epochs,
minibatch, learning rate and its schedule (:class:`UpdateSchedule`), gamma, lambda, clip,
gradient-norm clip, the KL stop (``ppo.target_kl``), entropy and value coefficients, no value
clipping unless ``ppo.vf_clip_coef``; reward times ``ppo.reward_scale`` and, with
``ppo.reward_norm: return``, SB3's own return normalisation (``VecNormalize(norm_obs=False,
norm_reward=True)``, its reward clip set out of reach).
``runtime.num_workers * runtime.envs_per_worker`` envs, each in its own process
(``SubprocVecEnv``) when there is more than one worker; every reset runs a random element of the
group (:class:`~covers_dist.bench.rllib_peer.PeerTask`).
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..config import Config
from .rllib_peer import peer_env, ppo_settings

__all__ = ["UpdateSchedule", "build_sb3_ppo", "sb3_hyperparameters", "sb3_greedy"]

#: VecNormalize's reward clip, set out of reach (covers-dist does not clip rewards).
_NO_CLIP = 1e9
#: SB3 stops an update at the first minibatch whose approximate KL (the same estimate as
#: covers-dist's) exceeds 1.5 x its ``target_kl``; covers-dist stops past ``ppo.target_kl`` itself.
_SB3_KL_FACTOR = 1.5


class UpdateSchedule:
    """SB3's ``learning_rate`` for covers-dist's schedule: ``lr``, or for ``linear``
    ``lr * max(0, 1 - k / horizon)`` at update k. SB3 passes the progress through the current
    ``learn()`` call, which ``bench learn`` makes one batch long, so the update count comes from the
    model's own env steps (``model`` is set once the model is built)."""

    def __init__(self, lr: float, schedule: str, horizon: int | None, batch: int) -> None:
        self.lr, self.schedule, self.horizon, self.batch = float(lr), schedule, horizon, int(batch)
        self.model: Any = None

    def __call__(self, _progress_remaining: float) -> float:
        from ..ppo.learner import scheduled_learning_rate

        # SB3 updates after each rollout: at update k the model has sampled k + 1 batches
        done = 0 if self.model is None else max(0, int(self.model.num_timesteps) // self.batch - 1)
        return scheduled_learning_rate(self.lr, self.schedule, done, self.horizon)


def build_sb3_ppo(cfg: Config, transforms: Sequence[str]) -> Any:
    """An SB3 PPO model on ``cfg``'s first task, each episode under a random one of ``transforms``."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    from ..config import config_to_dict

    if cfg.env.image_size < 36:
        raise ValueError(
            f"SB3's NatureCNN needs images of at least 36 px, env.image_size is {cfg.env.image_size}"
        )
    hp = ppo_settings(cfg)
    n_envs = cfg.runtime.num_workers * cfg.runtime.envs_per_worker
    base = {"config": config_to_dict(cfg), "task": cfg.env.tasks[0], "image_only": False,
            "transforms": list(transforms)}  # fmt: skip
    # the reward scale in each env (peer_env); the return normalisation is SB3's own, over all envs
    reward = {**hp["reward"], "normalize_return": False}
    makers = [partial(peer_env, {**base, "seed": cfg.seed + i, "reward": reward}) for i in range(n_envs)]
    if cfg.runtime.num_workers > 1 and n_envs > 1:
        venv: Any = SubprocVecEnv(makers, start_method="forkserver")
    else:
        venv = DummyVecEnv(makers)
    venv.seed(cfg.seed)
    if hp["reward"]["normalize_return"]:
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=hp["gamma"], clip_reward=_NO_CLIP)
    n_steps = max(1, hp["train_batch_env_steps"] // n_envs)
    torch.set_num_threads(max(1, cfg.runtime.num_cpus))
    schedule = UpdateSchedule(hp["lr"], hp["lr_schedule"], hp["lr_horizon_updates"], n_steps * n_envs)
    model = PPO(
        "MultiInputPolicy",
        venv,
        learning_rate=schedule,
        n_steps=n_steps,
        batch_size=hp["minibatch_size"],
        n_epochs=hp["epochs"],
        gamma=hp["gamma"],
        gae_lambda=hp["gae_lambda"],
        clip_range=hp["clip"],
        clip_range_vf=hp["value_clip"],
        normalize_advantage=hp["normalize_advantages"],
        ent_coef=hp["ent_coef"],
        vf_coef=hp["vf_coef"],
        max_grad_norm=hp["max_grad_norm"],
        target_kl=None if hp["target_kl"] is None else hp["target_kl"] / _SB3_KL_FACTOR,
        policy_kwargs={"net_arch": [cfg.network.hidden]},
        seed=cfg.seed,
        device="cpu",
        verbose=0,
    )
    schedule.model = model
    # SB3 would otherwise make a new empty SB3-<time> folder in the temp directory at every
    # learn() call (bench learn makes one a batch); a logger with no outputs writes nothing
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def sb3_hyperparameters(model: Any, cfg: Config) -> dict[str, Any]:
    """The effective hyperparameters of a built SB3 PPO, read back from the model."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    norm = model.get_vec_normalize_env()  # under SB3's own image transposition wrapper
    venv = model.get_env()
    while not isinstance(venv, (DummyVecEnv, SubprocVecEnv)) and hasattr(venv, "venv"):
        venv = venv.venv
    clip_vf = model.clip_range_vf(1.0) if model.clip_range_vf is not None else None
    return {
        "framework": "stable-baselines3",
        "network": f"MultiInputPolicy (CombinedExtractor: NatureCNN + proprio), net_arch [{cfg.network.hidden}]",
        "observation": "image + proprio",
        "train_batch_env_steps": int(model.n_steps * model.n_envs),
        "minibatch_size": int(model.batch_size),
        "epochs": int(model.n_epochs),
        **_lr_readback(model.learning_rate),
        "gamma": float(model.gamma),
        "gae_lambda": float(model.gae_lambda),
        "clip": float(model.clip_range(1.0)),
        "value_clip": clip_vf,
        "kl_loss": False,
        # the approximate KL at which an update stops (SB3 stops past 1.5 x its target_kl)
        "target_kl": None if model.target_kl is None else model.target_kl * _SB3_KL_FACTOR,
        "max_grad_norm": float(model.max_grad_norm),
        "ent_coef": float(model.ent_coef),
        "vf_coef": float(model.vf_coef),
        "normalize_advantages": "per minibatch" if model.normalize_advantage else False,
        "reward": {
            "scale": ppo_settings(cfg)["reward"]["scale"],
            "normalize_return": norm is not None and bool(norm.norm_reward),
            "gamma": float(model.gamma),
        },
        "envs": int(model.n_envs),
        "vec_env": type(venv).__name__,
    }


def _lr_readback(lr: UpdateSchedule) -> dict[str, Any]:
    horizon = lr.horizon if lr.schedule == "linear" else None
    return {"lr": lr.lr, "lr_schedule": lr.schedule, "lr_horizon_updates": horizon}


def sb3_greedy(model: Any) -> Callable[[Mapping[str, np.ndarray]], np.ndarray]:
    """The greedy policy of an SB3 model on a batch of dict observations (its ``predict``)."""

    def act(obs: Mapping[str, np.ndarray]) -> np.ndarray:
        actions, _ = model.predict({"image": np.asarray(obs["image"]), "proprio": np.asarray(obs["proprio"])},
                                   deterministic=True)  # fmt: skip
        return np.asarray(actions, dtype=np.float32)

    return act
