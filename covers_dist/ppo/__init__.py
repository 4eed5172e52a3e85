"""PPO math in pure torch: GAE, the clipped objective, the learner, and a serial collector.

Nothing here imports Ray; the runtime hosts :class:`PPOLearner` in its learner actors.
"""

from .gae import compute_gae
from .learner import EPISODE_KEYS, STAT_KEYS, PPOLearner, ReturnNormalizer, episodes_to_batch
from .loss import PPOLossTerms, normalize_advantages, ppo_loss
from .rollout import collect_episodes, success_rate

__all__ = [
    "compute_gae",
    "PPOLearner",
    "ReturnNormalizer",
    "episodes_to_batch",
    "EPISODE_KEYS",
    "STAT_KEYS",
    "ppo_loss",
    "PPOLossTerms",
    "normalize_advantages",
    "collect_episodes",
    "success_rate",
]
