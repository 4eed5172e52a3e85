"""RLlib's PPO on the same task as a covers-dist config: the peer ``bench train`` measures against.

RLlib's default catalog builds a CNN encoder for image observations, so the peer sees the same
top-down image (same renderer, same size) without the proprio vector, through a CNN whose
channel widths follow ``network.channels`` (stride-2 4x4 convolutions down to a small map).
Sampling uses ``runtime.num_workers`` env runners with ``runtime.envs_per_worker`` envs each, and
one train batch is one covers-dist iteration's worth of env steps.

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

__all__ = ["ImageOnlyTask", "build_rllib_ppo"]

#: Seed-sequence tag of the element draws (apart from the task instance's own use of the seed).
_TRANSFORM_TAG = 0x7D4


class ImageOnlyTask(gym.Env):
    """A covers-dist task with only the image (as floats in [0, 1]) as observation.

    ``env_config``: ``config`` (a config dict), ``task`` (a base task) and, optionally,
    ``transforms`` (a list of group element names, e.g. all of D4). Without ``transforms`` the task
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
        # RLlib's CNN encoder takes float input: the same image scaled to [0, 1]
        self.observation_space = gym.spaces.Box(0.0, 1.0, (size, size, 3), np.float32)
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
        return _scaled(obs["image"]), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.inner.step(action)
        return _scaled(obs["image"]), reward, terminated, truncated, info

    def close(self) -> None:
        for env in {id(e): e for e in [self.inner, *self._envs.values()]}.values():
            env.close()


def _scaled(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float32) * (1.0 / 255.0)


def build_rllib_ppo(cfg: Config, network: str = "default", transforms: list[str] | None = None) -> Any:
    """An RLlib PPO algorithm (new API stack) configured like ``cfg`` (Ray must be initialised).

    ``network="default"``: RLlib's own CNN on the image alone; ``"covers"``: covers-dist's network
    (``cfg.network``: the equivariant net or its CNN twin) as an RLModule on image + proprio
    (:mod:`covers_dist.integrations.rllib`), so the two frameworks are compared on equal compute.
    ``transforms`` (default network only): group element names; each episode then runs under a
    random one of them (:class:`ImageOnlyTask`) instead of the identity.
    """
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.tune.registry import register_env

    from ..config import config_to_dict

    if network not in ("default", "covers"):
        raise ValueError(f"network must be 'default' or 'covers', got {network!r}")
    if transforms is not None and network != "default":
        raise ValueError("transforms are supported with network='default' only")
    register_env("covers_image_task", lambda env_config: ImageOnlyTask(env_config))
    batch = cfg.clustering.update_every * cfg.env.max_episode_steps
    per_runner = max(1, batch // (cfg.runtime.num_workers * cfg.runtime.envs_per_worker))
    filters = []
    size = cfg.env.image_size
    for i, ch in enumerate(cfg.network.channels):
        if size <= 4:
            break
        filters.append([int(ch) * 4, 4, 2])  # ~ the equivariant net's width (regular fields x |D4| / 2)
        size //= 2
    if network == "covers":
        from ..integrations.rllib import covers_env_config, covers_rl_module_spec, register_covers_env

        env_name, env_config = register_covers_env(), covers_env_config(cfg)
        module = {"rl_module_spec": covers_rl_module_spec(cfg)}
    else:
        env_name, env_config = "covers_image_task", {"config": config_to_dict(cfg), "task": cfg.env.tasks[0]}
        if transforms is not None:
            env_config.update(transforms=list(transforms), seed=cfg.seed)
        module = {"model_config": DefaultModelConfig(conv_filters=filters, head_fcnet_hiddens=[cfg.network.hidden])}
    algo_cfg = (
        PPOConfig()
        .environment(env_name, env_config=env_config)
        .framework("torch")
        .env_runners(
            num_env_runners=cfg.runtime.num_workers,
            num_envs_per_env_runner=cfg.runtime.envs_per_worker,
            rollout_fragment_length=per_runner,
            num_cpus_per_env_runner=1,
        )
        .learners(num_learners=0)
        .training(
            train_batch_size_per_learner=batch,
            minibatch_size=min(cfg.ppo.minibatch_size, batch),
            num_epochs=cfg.ppo.epochs,
            lr=cfg.ppo.lr,
            gamma=cfg.ppo.gamma,
            lambda_=cfg.ppo.gae_lambda,
            clip_param=cfg.ppo.clip_coef,
        )
        .rl_module(**module)
        .debugging(seed=cfg.seed)
        .reporting(min_sample_timesteps_per_iteration=0)
    )
    return algo_cfg.build_algo()
