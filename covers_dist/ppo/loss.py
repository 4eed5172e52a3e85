"""The PPO-clip objective (Schulman et al. 2017; the COVERS paper's Equation 1) on one minibatch.

    ratio   = exp(log pi(a|s) - log pi_behaviour(a|s))        (behaviour log-probs stored with the data)
    L_pi    = mean( max(-A * ratio, -A * clip(ratio, 1 - eps, 1 + eps)) )
    L_V     = 0.5 * mean( max((V - R)^2, (V_old + clip(V - V_old, -c, c) - R)^2) )   (or unclipped)
    L_B     = mean( sum_i relu(|mu_i| - 1.1)^2 )                 (the mean's soft bound; rl_games' bounds loss)
    loss    = L_pi - ent_coef * mean(entropy) + vf_coef * L_V + bound_coef * L_B

Also returned, without gradients: the approximate KL ``mean((ratio - 1) - log ratio)`` (always
>= 0) and the fraction of samples whose ratio left the clip range.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["PPOLossTerms", "ppo_loss", "normalize_advantages", "bound_loss", "SOFT_BOUND"]

#: Where the soft bound on the Gaussian's mean starts (the action box is [-1, 1]).
SOFT_BOUND = 1.1


@dataclass
class PPOLossTerms:
    """The total loss (with gradients) and its parts (detached scalars)."""

    loss: torch.Tensor
    policy_loss: float
    value_loss: float
    entropy: float
    approx_kl: float
    clip_frac: float
    bound_loss: float = 0.0


def normalize_advantages(adv: torch.Tensor) -> torch.Tensor:
    """Zero mean, unit (population) standard deviation; a single sample maps to 0."""
    return (adv - adv.mean()) / (adv.std(unbiased=False) + 1e-8)


def bound_loss(mean: torch.Tensor, soft_bound: float = SOFT_BOUND) -> torch.Tensor:
    """``mean(sum_i relu(|mu_i| - soft_bound)^2)``: zero inside the box, quadratic beyond it.

    Invariant under sign flips and permutations of the entries, so it keeps a D4-equivariant
    policy's objective invariant."""
    return torch.relu(mean.abs() - soft_bound).pow(2).sum(-1).mean()


def ppo_loss(
    new_logp: torch.Tensor,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    new_values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    entropy: torch.Tensor,
    clip_coef: float,
    vf_clip_coef: float | None,
    ent_coef: float,
    vf_coef: float,
    mean: torch.Tensor | None = None,
    bound_coef: float = 0.0,
) -> PPOLossTerms:
    """The clipped surrogate, clipped value loss and entropy bonus (see module docs).

    ``advantages`` are used as given (normalize them first if wanted). With ``mean`` (the policy's
    mean actions, with gradients) and ``bound_coef`` > 0 the soft bound :func:`bound_loss` is added.
    """
    logratio = new_logp - old_logp
    ratio = logratio.exp()
    pg1 = -advantages * ratio
    pg2 = -advantages * torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef)
    policy_loss = torch.max(pg1, pg2).mean()
    unclipped = (new_values - returns).pow(2)
    if vf_clip_coef is None:
        value_loss = 0.5 * unclipped.mean()
    else:
        clipped_values = old_values + torch.clamp(new_values - old_values, -vf_clip_coef, vf_clip_coef)
        value_loss = 0.5 * torch.max(unclipped, (clipped_values - returns).pow(2)).mean()
    ent = entropy.mean()
    loss = policy_loss - ent_coef * ent + vf_coef * value_loss
    bound = None
    if mean is not None and bound_coef > 0:
        bound = bound_loss(mean)
        loss = loss + bound_coef * bound
    with torch.no_grad():
        approx_kl = ((ratio - 1.0) - logratio).mean()
        clip_frac = ((ratio - 1.0).abs() > clip_coef).float().mean()
    return PPOLossTerms(
        loss=loss,
        policy_loss=float(policy_loss.detach()),
        value_loss=float(value_loss.detach()),
        entropy=float(ent.detach()),
        approx_kl=float(approx_kl),
        clip_frac=float(clip_frac),
        bound_loss=0.0 if bound is None else float(bound.detach()),
    )
