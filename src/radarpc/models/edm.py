"""EDM (Karras et al., "Elucidating the Design Space of Diffusion-Based Generative Models", NeurIPS
2022): the denoiser's preconditioning, the training loss and the deterministic Heun sampler.

Everything here works on any denoiser ``D(x, sigma, condition) -> denoised`` with ``x`` of shape
``(B, ...)`` and ``sigma`` of shape ``(B,)`` (or a scalar): the latent diffusion model of
:mod:`radarpc.models.latent_dit` is one. Read top-down:

1. :func:`edm_coefficients` and :func:`edm_precondition`: the network ``F`` sees a unit-variance
   input and a log-noise level, and ``D = c_skip x + c_out F`` (EDM Table 1, "preconditioning");
2. :func:`edm_loss`: noise levels drawn log-normally, each weighted by ``lambda(sigma)`` (EDM
   Table 1, "training");
3. :func:`edm_sigma_steps` and :func:`edm_sampler`: the ``rho``-spaced noise levels and Heun's
   second-order steps along the probability-flow ODE (EDM Algorithm 2), with optional churn;
4. :class:`SeededNoise`: normal draws from one generator per sample, so that a sample's noise
   depends on its seed only, not on the batch it is drawn in.

The condition (RaLD's radar tokens) is an argument of the sampler, computed by the caller once and
handed unchanged to every one of the ``2 N - 1`` denoiser calls. Defaults are RaLD's (the
official ``EDMLoss`` and ``edm_sampler``): ``sigma_data = 1``, ``P_mean = -1.2``, ``P_std = 1.2``,
18 steps from 80 to 0.002 with ``rho = 7`` and no churn.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import torch

__all__ = [
    "Denoiser",
    "SeededNoise",
    "edm_coefficients",
    "edm_precondition",
    "edm_loss_weight",
    "edm_loss",
    "edm_sigma_steps",
    "edm_sampler",
]

Denoiser = Callable[[torch.Tensor, torch.Tensor, Any], torch.Tensor]
"""``D(x, sigma, condition) -> denoised``, ``x`` ``(B, ...)``, ``sigma`` ``(B,)`` or a scalar."""


# ----------------------------------------------------------------------------------------------
# Preconditioning
# ----------------------------------------------------------------------------------------------

def edm_coefficients(sigma: torch.Tensor, sigma_data: float = 1.0
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EDM's preconditioning coefficients at noise level ``sigma`` (elementwise)::

        c_skip  = sigma_data^2 / (sigma^2 + sigma_data^2)
        c_out   = sigma sigma_data / sqrt(sigma^2 + sigma_data^2)
        c_in    = 1 / sqrt(sigma^2 + sigma_data^2)
        c_noise = ln(sigma) / 4

    Parameters
    ----------
    sigma : Tensor
        Noise levels (standard deviation of the added Gaussian noise), > 0.
    sigma_data : float
        Standard deviation of the clean data.

    Returns
    -------
    (c_skip, c_out, c_in, c_noise) : tuple of Tensor
        Each of ``sigma``'s shape.
    """
    c_skip = sigma_data ** 2 / (sigma ** 2 + sigma_data ** 2)
    c_out = sigma * sigma_data / (sigma ** 2 + sigma_data ** 2).sqrt()
    c_in = 1 / (sigma_data ** 2 + sigma ** 2).sqrt()
    c_noise = sigma.log() / 4
    return c_skip, c_out, c_in, c_noise


def edm_precondition(net: Callable[[torch.Tensor, torch.Tensor, Any], torch.Tensor], x: torch.Tensor,
                     sigma: torch.Tensor | float, condition: Any, sigma_data: float = 1.0) -> torch.Tensor:
    """The denoiser ``D(x; sigma) = c_skip x + c_out F(c_in x; c_noise, condition)`` around a raw
    network ``F``.

    Parameters
    ----------
    net : callable
        The raw network ``F(x_in (B, ...), c_noise (B,) or (1,), condition) -> (B, ...)``.
    x : Tensor
        Noisy samples ``(B, ...)``, float32.
    sigma : Tensor or float
        Their noise levels: ``(B,)``, or one level for the whole batch (a scalar).
    condition : any
        Passed to ``net`` unchanged.
    sigma_data : float
        Standard deviation of the clean data.

    Returns
    -------
    Tensor
        ``D(x; sigma)``, of ``x``'s shape: the estimate of the clean sample.
    """
    sigma = torch.as_tensor(sigma, dtype=torch.float32, device=x.device)
    sigma = sigma.reshape(-1, *([1] * (x.ndim - 1)))                    # (B or 1, 1, ...)
    c_skip, c_out, c_in, c_noise = edm_coefficients(sigma, sigma_data)
    F_x = net(c_in * x, c_noise.flatten(), condition)
    return c_skip * x + c_out * F_x


# ----------------------------------------------------------------------------------------------
# Training loss
# ----------------------------------------------------------------------------------------------

def edm_loss_weight(sigma: torch.Tensor, sigma_data: float = 1.0) -> torch.Tensor:
    """The loss weight ``lambda(sigma) = (sigma^2 + sigma_data^2) / (sigma sigma_data)^2``, the
    inverse of ``c_out^2``: the weighted loss is the raw network's unit-variance target error."""
    return (sigma ** 2 + sigma_data ** 2) / (sigma * sigma_data) ** 2


def edm_loss(denoiser: Denoiser, y: torch.Tensor, condition: Any, *, P_mean: float = -1.2, P_std: float = 1.2,
             sigma_data: float = 1.0, generator: torch.Generator | None = None) -> torch.Tensor:
    """EDM's training loss on clean samples ``y``, averaged over every element::

        ln(sigma) ~ N(P_mean, P_std^2)           (one sigma per sample)
        n         ~ N(0, sigma^2 I)
        loss      = mean( lambda(sigma) (D(y + n; sigma, condition) - y)^2 )

    Parameters
    ----------
    denoiser : callable
        ``D(x, sigma (B,), condition)``.
    y : Tensor
        Clean samples ``(B, ...)`` (RaLD: the autoencoder's latents ``(B, M, D)``).
    condition : any
        Passed to ``denoiser`` unchanged.
    P_mean, P_std : float
        Mean and standard deviation of ``ln(sigma)``.
    sigma_data : float
        Standard deviation of the clean data.
    generator : torch.Generator, optional
        Draws ``sigma`` and the noise (in that order); the global generator without it.

    Returns
    -------
    Tensor
        The scalar loss.
    """
    shape = (y.shape[0],) + (1,) * (y.ndim - 1)
    rnd_normal = torch.randn(shape, generator=generator, device=y.device, dtype=y.dtype)
    sigma = (rnd_normal * P_std + P_mean).exp()                         # (B, 1, ...)
    weight = edm_loss_weight(sigma, sigma_data)
    n = torch.randn(y.shape, generator=generator, device=y.device, dtype=y.dtype) * sigma
    D_yn = denoiser(y + n, sigma.flatten(), condition)
    return (weight * (D_yn - y) ** 2).mean()


# ----------------------------------------------------------------------------------------------
# Sampler
# ----------------------------------------------------------------------------------------------

def edm_sigma_steps(num_steps: int = 18, sigma_min: float = 0.002, sigma_max: float = 80.0, rho: float = 7.0,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """The sampler's noise levels ``t_0 > t_1 > ... > t_{N-1}``, then ``t_N = 0``::

        t_i = (sigma_max^(1/rho) + i / (N - 1) (sigma_min^(1/rho) - sigma_max^(1/rho)))^rho

    computed in float32 (the official sampler's arithmetic).

    Returns
    -------
    Tensor
        ``(num_steps + 1,)`` float32.

    Raises
    ------
    ValueError
        ``num_steps < 2``, or not ``0 < sigma_min < sigma_max``, or ``rho <= 0``.
    """
    if int(num_steps) != num_steps or num_steps < 2:
        raise ValueError(f"edm sampler: num_steps must be an integer >= 2, got {num_steps!r}")
    if not (0 < sigma_min < sigma_max < math.inf):
        raise ValueError(f"edm sampler: need 0 < sigma_min < sigma_max < inf, got sigma_min={sigma_min}, "
                         f"sigma_max={sigma_max}")
    if not rho > 0:
        raise ValueError(f"edm sampler: rho must be > 0, got {rho}")
    i = torch.arange(num_steps, dtype=torch.float32, device=device)
    t_steps = (sigma_max ** (1 / rho) + i / (num_steps - 1) * (sigma_min ** (1 / rho) - sigma_max ** (1 / rho))) ** rho
    return torch.cat([t_steps, torch.zeros_like(t_steps[:1])])         # t_N = 0


def edm_sampler(denoiser: Denoiser, noise: torch.Tensor, condition: Any, *, num_steps: int = 18,
                sigma_min: float = 0.002, sigma_max: float = 80.0, rho: float = 7.0, S_churn: float = 0.0,
                S_min: float = 0.0, S_max: float = math.inf, S_noise: float = 1.0,
                randn_like: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Samples by Heun's method along EDM's probability-flow ODE (EDM Algorithm 2).

    From ``x_0 = t_0 noise``, each step ``i = 0 .. N-1`` (``t`` of :func:`edm_sigma_steps`)::

        gamma_i = min(S_churn / N, sqrt(2) - 1) if S_min <= t_i <= S_max else 0
        t_hat   = t_i + gamma_i t_i
        x_hat   = x_i + sqrt(t_hat^2 - t_i^2) S_noise eps,     eps ~ N(0, I)    (only if gamma_i > 0)
        d       = (x_hat - D(x_hat; t_hat)) / t_hat
        x_{i+1} = x_hat + (t_{i+1} - t_hat) d                                    (Euler)
        if i < N - 1:                                                            (2nd-order correction)
            d'      = (x_{i+1} - D(x_{i+1}; t_{i+1})) / t_{i+1}
            x_{i+1} = x_hat + (t_{i+1} - t_hat) (d + d') / 2

    ``2 N - 1`` calls of ``denoiser`` (35 for 18 steps), each with the same ``condition``. With
    ``S_churn = 0`` (the default) the sampler is deterministic: a function of ``noise`` and
    ``condition`` only.

    Parameters
    ----------
    denoiser : callable
        ``D(x, sigma (B,), condition)``; called under the caller's grad mode (wrap the call in
        ``torch.no_grad()`` to sample).
    noise : Tensor
        Standard normal initial noise ``(B, ...)``, float32 (e.g. from :class:`SeededNoise`).
    condition : any
        Computed once by the caller, passed unchanged to every denoiser call.
    num_steps, sigma_min, sigma_max, rho : see :func:`edm_sigma_steps`.
    S_churn, S_min, S_max, S_noise : float
        Stochasticity: total churn, the noise-level window it applies to, and the scale of the
        added noise.
    randn_like : callable, optional
        ``randn_like(x)``: the churn's standard normal draws, e.g. :meth:`SeededNoise.randn_like`.
        Required when churn applies (a sampler with churn is seeded through it).

    Returns
    -------
    Tensor
        The samples ``x_N``, of ``noise``'s shape.

    Raises
    ------
    ValueError
        Bad step settings (:func:`edm_sigma_steps`), ``S_churn < 0``, or churn without
        ``randn_like``.
    """
    if not S_churn >= 0:
        raise ValueError(f"edm sampler: S_churn must be >= 0, got {S_churn}")
    if S_churn > 0 and randn_like is None:
        raise ValueError("edm sampler: S_churn > 0 adds noise at every step; pass randn_like "
                         "(e.g. SeededNoise(seeds, device).randn_like) so that the samples are seeded")
    t_steps = edm_sigma_steps(num_steps, sigma_min, sigma_max, rho, device=noise.device)
    batch = noise.shape[0]

    x_next = noise * t_steps[0]
    for i, (t_cur, t_next) in enumerate(zip(t_steps[:-1], t_steps[1:])):   # 0, ..., N-1
        x_cur = x_next

        # increase the noise temporarily
        gamma = min(S_churn / num_steps, math.sqrt(2) - 1) if S_min <= t_cur <= S_max else 0.0
        t_hat = t_cur + gamma * t_cur
        x_hat = x_cur
        if gamma > 0:
            x_hat = x_cur + (t_hat ** 2 - t_cur ** 2).sqrt() * S_noise * randn_like(x_cur)

        # Euler step
        denoised = denoiser(x_hat, t_hat.expand(batch), condition)
        d_cur = (x_hat - denoised) / t_hat
        x_next = x_hat + (t_next - t_hat) * d_cur

        # second-order correction
        if i < num_steps - 1:
            denoised = denoiser(x_next, t_next.expand(batch), condition)
            d_prime = (x_next - denoised) / t_next
            x_next = x_hat + (t_next - t_hat) * (0.5 * d_cur + 0.5 * d_prime)
    return x_next


class SeededNoise:
    """Standard normal draws from one generator per sample, seeded by the sample's seed.

    Sample ``b``'s draws depend on ``seeds[b]`` only (the batch it is in, the batch size and the
    other seeds do not matter); this is how RaLD's official sampler seeds its initial latents
    (its ``StackedRandomGenerator``, each generator seeded with ``seed % 2**32``), so the same seeds
    give the same initial noise on the same device.

    Parameters
    ----------
    seeds : sequence of int
        One seed per sample.
    device : torch.device or str
        Where the generators (and the draws) live.
    """

    def __init__(self, seeds: Sequence[int], device: torch.device | str = "cpu"):
        seeds = [int(s) for s in seeds]
        if not seeds:
            raise ValueError("SeededNoise: give at least one seed")
        self.device = torch.device(device)
        self.generators = [torch.Generator(self.device).manual_seed(s % (1 << 32)) for s in seeds]

    def randn(self, shape: Sequence[int], dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """``(len(seeds), *shape[1:])`` standard normal values; ``shape[0]`` must be the number of seeds."""
        if shape[0] != len(self.generators):
            raise ValueError(f"SeededNoise: batch of {shape[0]} for {len(self.generators)} seeds")
        return torch.stack([torch.randn(tuple(shape[1:]), generator=g, dtype=dtype, device=self.device)
                            for g in self.generators])

    def randn_like(self, x: torch.Tensor) -> torch.Tensor:
        """Draws of ``x``'s shape and dtype (the sampler's churn noise)."""
        return self.randn(x.shape, dtype=x.dtype)
