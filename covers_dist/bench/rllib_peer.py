"""RLlib's PPO on the same task as a covers-dist config: the peer ``bench train`` and ``bench learn`` measure against.

Three networks (``build_rllib_ppo(cfg, network)``):

* ``"default"``: RLlib's default CNN encoder on the image alone (same renderer, same size, floats
  in [0, 1]), channel widths following ``network.channels`` (stride-2 4x4 convolutions down to a
  small map), a separate value network (``vf_share_layers=False``);
* ``"covers"``: covers-dist's own network (``cfg.network``: the equivariant net or, with
  ``network.kind=cnn``, its CNN twin) as an RLModule on image + proprio
  (:mod:`covers_dist.integrations.rllib`).

PPO is set on equal terms with covers-dist's learner (:func:`ppo_settings`): the same batch (one
covers-dist iteration: ``clustering.update_every`` episodes), epochs, minibatch, learning rate,
gamma, lambda, clip, gradient-norm clip, entropy and value coefficients; no value clipping
(``vf_clip_param`` infinite) unless ``ppo.vf_clip_coef`` is set; no KL loss unless
``ppo.target_kl`` is set; and the same reward treatment: rewards times ``ppo.reward_scale`` and,
with ``ppo.reward_norm: return``, divided by a running standard deviation of the discounted
return (gymnasium's ``NormalizeReward`` in each env, the per-env form of covers-dist's
normaliser). Sampling uses ``runtime.num_workers`` env runners with ``runtime.envs_per_worker``
envs each.

By default the peer trains on the base task only (the identity element, as ``bench train`` measures
throughput); with ``transforms`` (element names, ``env_config["transforms"]``) every reset runs a
random one of them, so RLlib trains on the same rotated and mirrored stream as covers-dist
(``bench learn``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from ..config import Config
from ..symmetry import GroupElement

__all__ = ["PeerTask", "ImageOnlyTask", "build_rllib_ppo", "ppo_settings", "peer_env"]

#: Seed-sequence tag of the element draws (apart from the task instance's own use of the seed).
_TRANSFORM_TAG = 0x7D4


class PeerTask(gym.Env):
    """A covers-dist task for another framework's PPO: image + proprio, or the image alone.

    ``env_config``: ``config`` (a config dict), ``task`` (a base task) and, optionally,
    ``image_only`` (default True: the image as floats in [0, 1] is the observation; False: the
    task's own dict ``{"image": uint8, "proprio"}``) and ``transforms`` (a list of group element
    names, e.g. all of D4). Without ``transforms`` the task
    always runs under the identity ``e``. With them, each reset draws one element uniformly from a
    generator seeded by the reset's seed, and a reset without a seed (RLlib's auto-resets) goes on
    drawing from the generator of the last seeded one (the element and the task instance's seed),
    so a seed fixes the element and the sequence of episodes after it. ``self.g`` is the element
    of the current episode.
    """

    metadata = {"render_modes": []}

    def __init__(self, env_config: dict[str, Any]) -> None:
        from ..config import config_from_dict
        from ..envs import make_task

        cfg = config_from_dict(env_config["config"])
        self._env_cfg, self._task = cfg.env, env_config["task"]
        names = env_config.get("transforms")
        if names is None:
            self.transforms: tuple[GroupElement, ...] | None = None
        else:
            if isinstance(names, str) or not names:
                raise ValueError(f"transforms must be a non-empty list of group element names, got {names!r}")
            self.transforms = tuple(GroupElement.from_name(str(n)) for n in names)
        first = self.transforms[0] if self.transforms else GroupElement()
        self.inner = make_task(cfg.env, self._task, first)
        self._envs: dict[str, Any] = {first.name: self.inner}  # per element, for envs without set_element
        self.g = first
        self._rng = np.random.default_rng(np.random.SeedSequence([int(env_config.get("seed", 0)), _TRANSFORM_TAG]))
        size = cfg.env.image_size
        self.image_only = bool(env_config.get("image_only", True))
        if self.image_only:  # RLlib's CNN encoder takes float input: the same image scaled to [0, 1]
            self.observation_space = gym.spaces.Box(0.0, 1.0, (size, size, 3), np.float32)
        else:
            self.observation_space = self.inner.observation_space
        self.action_space = self.inner.action_space

    def _switch(self, g: GroupElement) -> None:
        """Make ``self.inner`` the transformed task ``g.T`` (in place where the env supports it)."""
        if g == self.g:
            return
        if hasattr(self.inner, "set_element"):
            self.inner.set_element(g)
        else:
            env = self._envs.get(g.name)
            if env is None:
                from ..envs import make_task

                env = self._envs[g.name] = make_task(self._env_cfg, self._task, g)
            self.inner = env
        self.g = g

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if self.transforms is not None:
            if seed is not None:
                self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), _TRANSFORM_TAG]))
            self._switch(self.transforms[int(self._rng.integers(len(self.transforms)))])
            if seed is None:  # the instance too comes from the generator: reproducible after a seeded reset
                seed = int(self._rng.integers(2**31 - 1))
        obs, info = self.inner.reset(seed=seed)
        return self._obs(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.inner.step(action)
        return self._obs(obs), reward, terminated, truncated, info

    def _obs(self, obs: dict[str, np.ndarray]) -> Any:
        return _scaled(obs["image"]) if self.image_only else obs

    def close(self) -> None:
        for env in {id(e): e for e in [self.inner, *self._envs.values()]}.values():
            env.close()


#: The image-only peer env under its earlier name.
ImageOnlyTask = PeerTask


def peer_env(env_config: dict[str, Any]) -> gym.Env:
    """:class:`PeerTask` with covers-dist's reward treatment (``env_config["reward"]``: ``scale``,
    ``normalize_return`` and ``gamma``; absent: raw rewards)."""
    env: gym.Env = PeerTask(env_config)
    reward = env_config.get("reward")
    if reward:
        scale = float(reward["scale"])
        if scale != 1.0:
            env = gym.wrappers.TransformReward(env, lambda r: scale * r)
        if reward.get("normalize_return"):
            env = gym.wrappers.NormalizeReward(env, gamma=float(reward["gamma"]))
    return env


def reward_treatment(cfg: Config) -> dict[str, Any]:
    """covers-dist's reward treatment as the peers' env config."""
    return {
        "scale": float(cfg.ppo.reward_scale),
        "normalize_return": cfg.ppo.reward_norm == "return",
        "gamma": float(cfg.ppo.gamma),
    }


def ppo_settings(cfg: Config) -> dict[str, Any]:
    """The PPO hyperparameters every contender of ``bench learn`` shares, read from ``cfg``."""
    batch = cfg.steps_per_update
    return {
        "train_batch_env_steps": int(batch),
        "minibatch_size": int(min(cfg.ppo.minibatch_size, batch)),
        "epochs": int(cfg.ppo.epochs),
        "lr": float(cfg.ppo.lr),
        "lr_schedule": cfg.ppo.lr_schedule,
        "lr_horizon_updates": cfg.learner_ppo.total_updates if cfg.ppo.lr_schedule == "linear" else None,
        "gamma": float(cfg.ppo.gamma),
        "gae_lambda": float(cfg.ppo.gae_lambda),
        "clip": float(cfg.ppo.clip_coef),
        "value_clip": cfg.ppo.vf_clip_coef,
        "max_grad_norm": float(cfg.ppo.max_grad_norm),
        "ent_coef": float(cfg.ppo.ent_coef),
        "vf_coef": float(cfg.ppo.vf_coef),
        "target_kl": cfg.ppo.target_kl,
        "kl_loss": False,
        "normalize_advantages": bool(cfg.ppo.norm_adv),
        "reward": reward_treatment(cfg),
    }


def lr_setting(hp: dict[str, Any]) -> float | list[list[float]]:
    """RLlib's ``lr`` for covers-dist's schedule: the rate, or for ``linear`` the piecewise schedule
    from ``lr`` at 0 env steps to 0 after ``lr_horizon_updates`` train batches. RLlib sets the rate
    after each update from the env steps sampled so far, so its update k runs at
    ``lr * (1 - k / horizon)``, as covers-dist's learner does."""
    if hp["lr_schedule"] == "constant":
        return float(hp["lr"])
    end = int(hp["lr_horizon_updates"]) * int(hp["train_batch_env_steps"])
    return [[0, float(hp["lr"])], [end, 0.0]]


def _lr_readback(lr: Any, batch: int) -> dict[str, Any]:
    if isinstance(lr, (list, tuple)):
        return {"lr": float(lr[0][1]), "lr_schedule": "linear", "lr_horizon_updates": int(lr[-1][0]) // batch}
    return {"lr": float(lr), "lr_schedule": "constant", "lr_horizon_updates": None}


def _scaled(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float32) * (1.0 / 255.0)


def build_rllib_ppo(
    cfg: Config, network: str = "default", transforms: list[str] | None = None, equal_terms: bool = True
) -> Any:
    """An RLlib PPO algorithm (new API stack) configured like ``cfg`` (Ray must be initialised).

    ``network="default"``: RLlib's own CNN on the image alone; ``"covers"``: covers-dist's network
    (``cfg.network``: the equivariant net or its CNN twin) as an RLModule on image + proprio
    (:mod:`covers_dist.integrations.rllib`). ``transforms``: group element names; each episode then
    runs under a random one of them instead of the identity. ``equal_terms`` (default): covers-dist's
    reward treatment, no value clip, no KL loss, its gradient clip and coefficients
    (:func:`ppo_settings`); False: RLlib's own defaults for those (raw reward, ``vf_clip_param=10``,
    the KL loss), as ``bench train`` measures throughput.
    """
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.tune.registry import register_env

    from ..config import config_to_dict

    if network not in ("default", "covers"):
        raise ValueError(f"network must be 'default' or 'covers', got {network!r}")
    register_env("covers_peer_task", peer_env)
    hp = ppo_settings(cfg)
    batch = hp["train_batch_env_steps"]
    per_runner = max(1, batch // (cfg.runtime.num_workers * cfg.runtime.envs_per_worker))
    env_config: dict[str, Any] = {
        "config": config_to_dict(cfg),
        "task": cfg.env.tasks[0],
        "image_only": network == "default",
        "seed": cfg.seed,
    }
    if transforms is not None:
        env_config["transforms"] = list(transforms)
    if equal_terms:
        env_config["reward"] = hp["reward"]
    if network == "covers":
        from ..integrations.rllib import covers_rl_module_spec

        module = {"rl_module_spec": covers_rl_module_spec(cfg)}
    else:
        filters = []
        size = cfg.env.image_size
        for ch in cfg.network.channels:
            if size <= 4:
                break
            filters.append([int(ch) * 4, 4, 2])  # ~ the equivariant net's width (regular fields x |D4| / 2)
            size //= 2
        model = DefaultModelConfig(
            conv_filters=filters, head_fcnet_hiddens=[cfg.network.hidden], vf_share_layers=not equal_terms
        )
        module = {"model_config": model}
    training: dict[str, Any] = dict(
        train_batch_size_per_learner=batch,
        minibatch_size=hp["minibatch_size"],
        num_epochs=hp["epochs"],
        lr=lr_setting(hp),
        gamma=hp["gamma"],
        lambda_=hp["gae_lambda"],
        clip_param=hp["clip"],
    )
    if equal_terms:
        training.update(
            vf_clip_param=float("inf") if hp["value_clip"] is None else float(hp["value_clip"]),
            use_kl_loss=hp["target_kl"] is not None,
            kl_coeff=0.0 if hp["target_kl"] is None else 0.2,
            kl_target=0.01 if hp["target_kl"] is None else float(hp["target_kl"]),
            grad_clip=hp["max_grad_norm"],
            grad_clip_by="global_norm",
            entropy_coeff=hp["ent_coef"],
            vf_loss_coeff=hp["vf_coef"],
        )
    algo_cfg = (
        PPOConfig()
        .environment("covers_peer_task", env_config=env_config)
        .framework("torch")
        .env_runners(
            num_env_runners=cfg.runtime.num_workers,
            num_envs_per_env_runner=cfg.runtime.envs_per_worker,
            rollout_fragment_length=per_runner,
            num_cpus_per_env_runner=1,
        )
        .learners(num_learners=0)
        .training(**training)
        .rl_module(**module)
        .debugging(seed=cfg.seed)
        .reporting(min_sample_timesteps_per_iteration=0)
    )
    return algo_cfg.build_algo()


def rllib_hyperparameters(algo: Any, network: str, cfg: Config) -> dict[str, Any]:
    """The effective hyperparameters of a built RLlib PPO, read back from its config."""
    c = algo.config
    env_config = dict(c.env_config)
    model = c.model_config if network == "default" else None
    return {
        "framework": "rllib",
        "network": "rllib default CNN on the image" if network == "default" else f"covers-dist {cfg.network.kind} (RLModule)",
        "observation": "image" if network == "default" else "image + proprio",
        "train_batch_env_steps": int(c.train_batch_size_per_learner),
        "minibatch_size": int(c.minibatch_size),
        "epochs": int(c.num_epochs),
        **_lr_readback(c.lr, int(c.train_batch_size_per_learner)),
        "gamma": float(c.gamma),
        "gae_lambda": float(c.lambda_),
        "clip": float(c.clip_param),
        "value_clip": None if c.vf_clip_param == float("inf") else float(c.vf_clip_param),
        "kl_loss": bool(c.use_kl_loss),
        "max_grad_norm": None if c.grad_clip is None else float(c.grad_clip),
        "ent_coef": float(c.entropy_coeff),
        "vf_coef": float(c.vf_loss_coeff),
        "normalize_advantages": "over the train batch (RLlib's GAE connector)",
        "reward": env_config.get("reward") or "raw",
        "vf_share_layers": None if model is None else bool(getattr(model, "vf_share_layers", True)),
        "env_runners": int(c.num_env_runners),
        "envs_per_env_runner": int(c.num_envs_per_env_runner),
    }
