"""The covers-dist actor-critic (equivariant or CNN twin) as an RLlib RLModule (new API stack).

RLlib users can train the project's network with RLlib's PPO::

    from covers_dist.config import load_config
    from covers_dist.integrations.rllib import covers_rl_module_spec, register_covers_env

    cfg = load_config("configs/quickstart.yaml")
    env_name = register_covers_env()
    ppo = (PPOConfig().environment(env_name, env_config=covers_env_config(cfg))
           .rl_module(rl_module_spec=covers_rl_module_spec(cfg)) ...)

The module wraps :func:`covers_dist.models.build_actor_critic`: observations are the tasks' own
dicts (``image`` uint8 (S, S, 3), ``proprio``), the action distribution is RLlib's diagonal
Gaussian over ``[mean, log_std]`` (the same state-independent, pair-tied log-std as covers-dist's
policy), and the value comes from the core's invariant features (passed to ``compute_values`` as
RLlib's embeddings, so PPO's loss runs the network once per minibatch). Exploration and inference
use the exported no-grad core (the path covers-dist's rollout workers use); training uses the
escnn modules, so the equivariance is the same as in covers-dist.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis import ValueFunctionAPI
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.core.rl_module.torch import TorchRLModule

from ..config import Config, NetworkConfig, config_from_dict, config_to_dict

__all__ = ["CoversRLModule", "CoversTaskEnv", "covers_rl_module_spec", "covers_env_config", "register_covers_env"]

ENV_NAME = "covers_task"


class CoversRLModule(TorchRLModule, ValueFunctionAPI):
    """``model_config``: ``{"network": NetworkConfig fields, "suite": ..., "image_size": ..., "seed": ...}``."""

    def setup(self) -> None:
        from ..envs import suite_layout
        from ..models import build_actor_critic

        mc = dict(self.model_config or {})
        net = NetworkConfig(**mc["network"])
        if net.critic != "shared":  # compute_values reads the value head off the policy's features
            raise ValueError(f"network.critic={net.critic}: the RLlib module supports the shared critic only")
        layout = suite_layout(mc["suite"], int(mc["image_size"]))
        self.net = build_actor_critic(net, layout, seed=mc.get("seed"))

    def get_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        """The learnable parameters only (``ActorCritic.get_weights``): escnn keeps eval-mode filter
        caches as buffers, which a train-mode learner and an eval-mode env runner do not share."""
        return {f"net.{name}": w for name, w in self.net.get_weights().items()}

    def set_state(self, state: dict[str, Any]) -> None:
        weights = {k.removeprefix("net."): torch.as_tensor(v) for k, v in state.items() if k.startswith("net.")}
        self.net.set_weights({k: v for k, v in weights.items() if k in dict(self.net.named_parameters())})

    def _core(self, batch: dict[str, Any], fast: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        obs = batch[Columns.OBS]
        image, proprio = obs["image"], obs["proprio"]
        img = image.permute(0, 3, 1, 2).to(torch.float32)
        if image.dtype == torch.uint8 or float(img.max()) > 1.0:
            img = img / 255.0
        proprio = proprio.to(torch.float32)
        if fast:
            with torch.no_grad():
                return self.net.fast_core()(img.contiguous(memory_format=torch.channels_last), proprio)
        return self.net.core(img, proprio)

    def _dist_inputs(self, mean: torch.Tensor) -> torch.Tensor:
        mean = self.net.policy_mean(mean)
        return torch.cat([mean, self.net.log_std().expand_as(mean)], dim=-1)

    def _forward(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        mean, _, _ = self._core(batch, fast=True)
        return {Columns.ACTION_DIST_INPUTS: self._dist_inputs(mean)}

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        mean, _, features = self._core(batch, fast=False)
        return {Columns.ACTION_DIST_INPUTS: self._dist_inputs(mean.float()), Columns.EMBEDDINGS: features}

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        if embeddings is None:
            embeddings = self._core(batch, fast=False)[2]
        return self.net.core.value_head(embeddings).squeeze(-1).float()


class CoversTaskEnv(gym.Env):
    """A covers-dist task (image + proprio dict observations) for RLlib's env runners."""

    metadata = {"render_modes": []}

    def __init__(self, env_config: dict[str, Any]) -> None:
        from ..envs import make_task

        cfg = config_from_dict(env_config["config"])
        self.inner = make_task(cfg.env, env_config["task"], env_config.get("g", "e"))
        self.observation_space = self.inner.observation_space
        self.action_space = self.inner.action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        return self.inner.reset(seed=seed)

    def step(self, action: np.ndarray):
        return self.inner.step(action)

    def close(self) -> None:
        self.inner.close()


def covers_rl_module_spec(cfg: Config, seed: int | None = None) -> RLModuleSpec:
    """An RLModuleSpec building ``cfg.network`` for ``cfg.env``'s observations."""
    return RLModuleSpec(
        module_class=CoversRLModule,
        model_config={
            "network": config_to_dict(cfg)["network"],
            "suite": cfg.env.suite,
            "image_size": cfg.env.image_size,
            "seed": cfg.seed if seed is None else seed,
        },
    )


def covers_env_config(cfg: Config, task: str | None = None, g: str = "e") -> dict[str, Any]:
    """``env_config`` for :class:`CoversTaskEnv`: the config's first task (or ``task``) under ``g``."""
    return {"config": config_to_dict(cfg), "task": task or cfg.env.tasks[0], "g": g}


def register_covers_env(name: str = ENV_NAME) -> str:
    """Register :class:`CoversTaskEnv` with Ray Tune under ``name``; returns the name."""
    from ray.tune.registry import register_env

    register_env(name, lambda env_config: CoversTaskEnv(env_config))
    return name
