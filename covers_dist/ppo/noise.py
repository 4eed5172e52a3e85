"""Temporally correlated (coloured) Gaussian action noise for exploration.

A Gaussian policy usually draws its exploration noise afresh at every step (white noise): over
an episode the hand then wanders like a random walk and rarely moves far in one direction.
Coloured noise keeps the marginal of every step a standard normal, so an action is still
distributed as ``N(mean, std)`` and PPO's log-probabilities and ratios are unchanged, but draws
the sequence of one episode with a power spectrum ``1 / f**beta``: ``beta = 0`` is white noise,
``beta = 1`` pink, ``beta = 2`` red (Brownian-like). Low frequencies carry more of the variance as
``beta`` grows, so the noise of consecutive steps points the same way for longer (Eberhard et al.,
"Pink Noise Is All You Need", ICLR 2023, found pink noise a good default for continuous control).

Coloured noise helps a policy find a success that lies off its mean's path and can slow one whose
success asks for precision (docs/research/learning.md); :func:`faded_beta` lets the colour fade to white
as a policy's own training episodes succeed, so one setting can serve both.

Plain module: torch only, no runtime imports.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = [
    "FADE_WINDOW",
    "NOISE_ENTRIES",
    "coloured_noise",
    "coloured_entries",
    "coloured_episode",
    "faded_beta",
    "NoiseSequences",
]

#: Training episodes of a policy whose success fades its colour (``ppo.noise_fade_success``).
FADE_WINDOW = 64

#: Which action entries get the colour (``ppo.noise_entries``); the others keep white noise.
NOISE_ENTRIES = ("all", "planar", "scalar")


def coloured_entries(entries: str, action_dim: int, action_pairs: int) -> list[bool] | None:
    """Per action entry, whether it gets the colour under ``ppo.noise_entries`` (None: every entry).

    The group acts on the first ``2 * action_pairs`` entries (table-plane pairs: rotated and
    mirrored) and leaves the rest (height, gripper) alone. A noise law is invariant under the group
    when each pair's two entries share one law, so the choice is made per kind, never per entry:
    ``planar`` colours the pairs only, ``scalar`` the others only.
    """
    if entries not in NOISE_ENTRIES:
        raise ValueError(f"noise entries must be one of {', '.join(NOISE_ENTRIES)}, got {entries!r}")
    if not 0 <= 2 * action_pairs <= action_dim:
        raise ValueError(f"need 0 <= 2 * action_pairs <= action_dim, got {action_pairs} pairs for {action_dim} entries")
    if entries == "all":
        return None
    planar = [i < 2 * action_pairs for i in range(action_dim)]
    return planar if entries == "planar" else [not p for p in planar]


def coloured_noise(
    beta: float,
    steps: int,
    dims: int,
    generator: torch.Generator | None = None,
    coloured: Sequence[bool] | None = None,
) -> torch.Tensor:
    """A ``(steps, dims)`` float32 tensor: ``dims`` independent sequences of ``steps`` standard
    normal samples whose power spectrum falls as ``1 / f**beta``.

    Every entry is exactly ``N(0, 1)`` (a linear map of independent normals, scaled by its exact
    standard deviation); ``beta = 0`` draws plain independent normals. ``coloured`` (one flag per
    dim, :func:`coloured_entries`) keeps the flagged dims coloured and gives the others white noise,
    drawn after the coloured sequences (None or all flags set: the draws are those of every dim
    coloured).
    """
    if coloured is not None and len(coloured) != dims:
        raise ValueError(f"need one coloured flag per dim, got {len(coloured)} for {dims} dims")
    x = _coloured(beta, steps, dims, generator)
    if coloured is not None and not all(coloured) and beta != 0.0:
        white = torch.randn(steps, dims, generator=generator)
        keep = torch.tensor([bool(c) for c in coloured])
        x = torch.where(keep, x, white)
    return x


def _coloured(beta: float, steps: int, dims: int, generator: torch.Generator | None) -> torch.Tensor:
    if not beta >= 0.0:
        raise ValueError(f"beta must be >= 0, got {beta!r}")
    if steps < 1 or dims < 1:
        raise ValueError(f"need steps >= 1 and dims >= 1, got {steps} and {dims}")
    if beta == 0.0 or steps == 1:
        return torch.randn(steps, dims, generator=generator)
    freqs = torch.fft.rfftfreq(steps, dtype=torch.float64)  # 0, 1/steps, ..., 1/2
    freqs[0] = freqs[1]  # the mean's component gets the lowest frequency's weight
    scale = freqs ** (-beta / 2.0)
    n = len(freqs)
    real = torch.randn(n, dims, generator=generator, dtype=torch.float64)
    imag = torch.randn(n, dims, generator=generator, dtype=torch.float64)
    imag[0] = 0.0  # the mean is real
    # each entry of irfft(X) is (1/steps) * (X_0 + 2 Re sum_k X_k e^{...} [+ X_nyq (-1)^t]);
    # its variance from the scaled components, so every entry can be made exactly N(0, 1)
    weights = torch.full((n,), 4.0, dtype=torch.float64)
    weights[0] = 1.0
    if steps % 2 == 0:
        imag[-1] = 0.0  # the Nyquist component is real too
        weights[-1] = 1.0
    std = torch.sqrt((weights * scale**2).sum()) / steps
    spectrum = torch.complex(real, imag) * scale[:, None]
    x = torch.fft.irfft(spectrum, n=steps, dim=0) / std
    return x.to(torch.float32)


def coloured_episode(episode_index: int, fraction: float) -> bool:
    """Whether training episode ``episode_index`` gets the coloured noise when only ``fraction`` of
    the episodes do (``ppo.noise_fraction``): spread evenly over the indices (0.5: every second
    episode, the odd ones), a pure function of the index so a retried batch samples the same."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction!r}")
    return int((episode_index + 1) * fraction) > int(episode_index * fraction)


def faded_beta(beta: float, fade_success: float | None, successes: list[float]) -> float:
    """The colour a policy samples with: ``beta`` faded linearly to white as its success rate over
    ``successes`` (its latest training episodes, 1 or 0 each) rises to ``fade_success``.

    ``fade_success`` None keeps ``beta``; a policy with no episodes yet gets ``beta``.
    """
    if fade_success is None or beta == 0.0 or not successes:
        return float(beta)
    if not fade_success > 0.0:
        raise ValueError(f"fade_success must be > 0 or None, got {fade_success!r}")
    rate = sum(1.0 for s in successes if s > 0.0) / len(successes)
    return float(beta) * max(0.0, 1.0 - rate / fade_success)


class NoiseSequences:
    """One coloured-noise sequence per environment of a lockstep batch, drawn at the episode's
    start; ``take(i, t)`` is env ``i``'s standard-normal noise vector for its step ``t``.

    An episode that runs past ``steps`` gets a fresh sequence appended (the sequences are drawn in
    env order, so a generator fixes them all).
    """

    def __init__(
        self,
        beta: float | Sequence[float],
        steps: int,
        dims: int,
        envs: int,
        generator: torch.Generator | None,
        coloured: Sequence[bool] | None = None,
    ) -> None:
        self.betas = [float(b) for b in beta] if isinstance(beta, Sequence) else [float(beta)] * envs
        if len(self.betas) != envs:
            raise ValueError(f"need one beta per env, got {len(self.betas)} for {envs} envs")
        self.steps, self.dims = int(steps), int(dims)
        self.generator = generator
        self.coloured = None if coloured is None else [bool(c) for c in coloured]
        self._seqs = [coloured_noise(b, self.steps, self.dims, generator, self.coloured) for b in self.betas]

    def take(self, i: int, t: int) -> torch.Tensor:
        while t >= len(self._seqs[i]):
            more = coloured_noise(self.betas[i], self.steps, self.dims, self.generator, self.coloured)
            self._seqs[i] = torch.cat([self._seqs[i], more])
        return self._seqs[i][t]
