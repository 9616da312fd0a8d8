"""RaLD's LiDAR autoencoder: a KL vector-set autoencoder (3DShape2VecSet) that encodes a point cloud
into ``M`` latent vectors and decodes the occupancy of arbitrary query points.

The seed's autoencoder (Sec. "Frustum-Based LiDAR Autoencoder" and "Order-Invariant Latent
Encoding"), read top-down in :class:`VecSetAutoencoder`:

1. **Point embedding** (:class:`FourierEmbedding`). A point ``p = (x, y, z)`` in ``[-1, 1]^3`` is
   lifted to ``[sin(pi 2^k p_a), cos(pi 2^k p_a), p]`` for ``k = 0..F-1`` and each axis ``a``
   (``6 F + 3`` features, 51 for ``F = 8``), then a linear layer maps it to width ``C``. The same
   embedding serves the input points and the decoder's query points.
2. **Encoder queries** ``Q_enc`` ``(M, C)``, by :attr:`VecSetAEConfig.query_type`:

   * ``"hybrid"`` (RaLD, Eq. 9): ``Q_enc = Proj(Q_s + CrossAttn(Q_d, P))`` with learned static
     queries ``Q_s`` and learned dynamic queries ``Q_d`` that attend to the embedded points ``P``;
   * ``"static"``: ``Q_enc = Q_s``, learned queries only;
   * ``"fps"``: the embeddings of ``M`` input points chosen by farthest point sampling
     (3DShape2VecSet's point queries; the only type whose latents depend on the input order, through
     the first point chosen).

3. **Encoder**: one pre-norm cross-attention block from ``Q_enc`` to ``P`` and a GEGLU
   feed-forward, both residual, then two linear maps give the posterior's mean ``mu`` and
   log-variance ``log sigma^2`` ``(M, D)``; ``z = mu + sigma * eps``, ``eps ~ N(0, I)``.
4. **Decoder**: ``z`` back to width ``C`` by a linear map, ``depth`` pre-norm self-attention
   blocks (attention and GEGLU feed-forward, residual, with stochastic depth while training), and
   a single-head cross-attention from the embedded queries to these tokens followed by a linear
   map to one occupancy logit per query.

Every attention is ``softmax(q k^T / sqrt(d_head)) v`` over the whole set
(:func:`torch.nn.functional.scaled_dot_product_attention`); no positional index enters, so the
encoder is invariant to the order of the input points (static and hybrid queries) and each query's
logit depends on that query alone.

The model is agnostic of the occupancy partitioning: it reads point and query coordinates already
normalised to ``[-1, 1]`` per axis (RaLD normalises polar range, azimuth and elevation over its
frustum grid, :func:`radarpc.rald.frustum.normalize`); which cells make a query occupied, RaLD's
frustums or Cartesian voxels, is the data's choice (:func:`radarpc.rald.voxels.partition_grid`,
:func:`radarpc.rald.voxels.model_coords`).

Losses: :func:`occupancy_loss` (BCE, weighted separately on occupied and empty queries) and
:func:`kl_divergence`; :meth:`VecSetAutoencoder.loss` adds them with the config's weights.

Size variants (listed in :data:`radarpc.models.MODELS`): :func:`rald_ae` (the official
``kl_d512_m512_l32_mix``, 108,002,881 parameters), :func:`rald_ae_s` (trains on CPU) and
:func:`rald_ae_tiny` (tests).

Official weights. The module mirrors the official ``KLAutoEncoder``'s layout, so its state dict
maps by renaming keys alone (no tensor is split, merged or transposed): :func:`official_key`.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = [
    "QUERY_TYPES",
    "OFFICIAL_KEY_MAP",
    "OFFICIAL_QUERY_TYPES",
    "official_key",
    "VecSetAEConfig",
    "VecSetAutoencoder",
    "FourierEmbedding",
    "FoldedDecoder",
    "Attention",
    "FeedForward",
    "LatentBlock",
    "farthest_point_sample",
    "occupancy_loss",
    "kl_divergence",
    "rald_ae",
    "rald_ae_s",
    "rald_ae_tiny",
]

QUERY_TYPES: tuple[str, ...] = ("hybrid", "static", "fps")
"""Encoder query types: RaLD's hybrid queries, learned static queries, farthest-point-sampled points."""

LOGVAR_RANGE = (-30.0, 20.0)
"""The posterior log-variance is clamped to this range (as the official code), so ``exp`` stays finite."""

OFFICIAL_KEY_MAP: tuple[tuple[str, str], ...] = (
    # (pattern, replacement) for re.sub, applied in order: the first group renames the module,
    # the second the layers inside the official PreNorm / FeedForward wrappers
    (r"^point_embed\.mlp\.", "embed.proj."),
    (r"^(s_)?latents\.weight$", "static_queries"),     # "s_latents" of query type "mix", "latents" of "learnable"
    (r"^d_latents\.weight$", "dynamic_queries"),
    (r"^mix_attn_layer\.", "query_attn."),
    (r"^cross_attend_blocks\.0\.", "encoder_attn."),
    (r"^cross_attend_blocks\.1\.", "encoder_ff."),
    (r"^mean_fc\.", "to_mean."),
    (r"^logvar_fc\.", "to_logvar."),
    (r"^proj\.", "from_latents."),
    (r"^layers\.(\d+)\.0\.", r"blocks.\1.attn."),
    (r"^layers\.(\d+)\.1\.", r"blocks.\1.ff."),
    (r"^decoder_cross_attn\.", "decoder_attn."),
    (r"^to_outputs\.", "to_logit."),
    (r"\.fn\.net\.0\.", ".fc1."),
    (r"\.fn\.net\.2\.", ".fc2."),
    (r"\.fn\.", "."),
)
"""How the official ``KLAutoEncoder``'s state-dict keys become this module's (:func:`official_key`).

Only names change: no tensor is split, merged or transposed (``query_proj`` keeps its name).
The official ``point_embed.basis`` buffer (``pi 2^k`` on a block diagonal) has no counterpart:
this module computes the frequencies from :attr:`VecSetAEConfig.fourier_freqs`. The official
``decoder_ff`` is disabled in every official config and has none either.
"""

OFFICIAL_QUERY_TYPES = {"mix": "hybrid", "learnable": "static", "point": "fps"}
"""The official ``query_type`` names and radarpc's."""


def official_key(key: str) -> str | None:
    """This module's state-dict key for an official ``KLAutoEncoder`` key; None for
    ``point_embed.basis``, which this module does not store.

    Example: ``layers.3.1.fn.net.0.weight`` -> ``blocks.3.ff.fc1.weight``.
    """
    if key == "point_embed.basis":
        return None
    for pattern, repl in OFFICIAL_KEY_MAP:
        key = re.sub(pattern, repl, key)
    return key


# ----------------------------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class VecSetAEConfig:
    """A vector-set occupancy autoencoder, whole.

    The defaults are the official ``kl_d512_m512_l32_mix`` (108,002,881 parameters).
    """

    width: int = 512              # C: token width of the encoder, the latent transformer and the decoder
    depth: int = 24               # self-attention blocks of the decoder's latent transformer
    heads: int = 8                # heads of those blocks and of the hybrid queries' attention
    head_dim: int = 64            # width per head (heads * head_dim: the attention's inner width)
    n_latents: int = 512          # M: latent vectors per frame
    latent_dim: int = 32          # D: width of a latent vector (the diffusion model's token width)
    fourier_freqs: int = 8        # F: frequencies pi 2^k, k = 0..F-1, per axis of the point embedding
    ff_mult: int = 4              # GEGLU feed-forward hidden width = ff_mult * width
    query_type: str = "hybrid"    # encoder queries: "hybrid", "static" or "fps" (QUERY_TYPES)
    drop_path: float = 0.1        # stochastic-depth rate of the latent blocks and the hybrid queries' attention
    kl_weight: float = 1e-3       # weight of the KL term in the loss
    occupied_weight: float = 0.1  # weight of the mean BCE over occupied queries
    empty_weight: float = 1.0     # weight of the mean BCE over empty queries

    def __post_init__(self) -> None:
        for k in ("width", "depth", "heads", "head_dim", "n_latents", "latent_dim", "fourier_freqs", "ff_mult"):
            v = getattr(self, k)
            if isinstance(v, bool) or int(v) != v:
                raise ValueError(f"VecSetAEConfig.{k} must be an integer, got {v!r}")
            object.__setattr__(self, k, int(v))
            if int(v) < (0 if k == "depth" else 1):
                raise ValueError(f"VecSetAEConfig.{k} must be >= {0 if k == 'depth' else 1}, got {v}")
        if self.query_type not in QUERY_TYPES:
            raise ValueError(f"VecSetAEConfig.query_type must be one of {list(QUERY_TYPES)}, got {self.query_type!r}")
        if not (isinstance(self.drop_path, (int, float)) and 0.0 <= self.drop_path < 1.0):
            raise ValueError(f"VecSetAEConfig.drop_path must be in [0, 1), got {self.drop_path!r}")
        for k in ("kl_weight", "occupied_weight", "empty_weight"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"VecSetAEConfig.{k} must be a finite weight >= 0, got {v!r}")
            object.__setattr__(self, k, float(v))
        object.__setattr__(self, "drop_path", float(self.drop_path))

    @property
    def embed_features(self) -> int:
        """Width of the Fourier features of a point, ``6 F + 3``."""
        return 6 * self.fourier_freqs + 3


# ----------------------------------------------------------------------------------------------
# Model
# ----------------------------------------------------------------------------------------------

class VecSetAutoencoder(nn.Module):
    """RaLD's occupancy autoencoder (see the module docstring).

    ``forward(points, queries)`` takes a LiDAR cloud ``(B, N, 3)`` and query points ``(B, Q, 3)``,
    both normalised to ``[-1, 1]`` per axis, and returns the occupancy logits ``(B, Q)`` and the KL
    divergence of each frame's posterior ``(B,)``.
    """

    input_kind = "lidar"          # forward takes dense (B, N, 3) normalised LiDAR points and (B, Q, 3) queries

    def __init__(self, cfg: VecSetAEConfig):
        super().__init__()
        self.cfg = cfg
        c, m = cfg.width, cfg.n_latents
        self.embed = FourierEmbedding(cfg.fourier_freqs, c)
        # encoder queries
        self.static_queries = (nn.Parameter(torch.randn(m, c)) if cfg.query_type in ("hybrid", "static")
                               else None)                                                       # (M, C)
        if cfg.query_type == "hybrid":
            self.dynamic_queries = nn.Parameter(torch.randn(m, c))                              # (M, C)
            self.query_attn = Attention(c, heads=cfg.heads, head_dim=cfg.head_dim, context_dim=c,
                                        norm_context=False)
            self.query_proj = nn.Linear(c, c)
        else:
            self.dynamic_queries = self.query_attn = self.query_proj = None
        # encoder: one cross-attention block to the points, then the posterior
        self.encoder_attn = Attention(c, heads=1, head_dim=c, context_dim=c)
        self.encoder_ff = FeedForward(c, cfg.ff_mult)
        self.to_mean = nn.Linear(c, cfg.latent_dim)
        self.to_logvar = nn.Linear(c, cfg.latent_dim)
        # decoder: latent transformer, then a cross-attention from the queries
        self.from_latents = nn.Linear(cfg.latent_dim, c)
        self.blocks = nn.ModuleList(LatentBlock(cfg) for _ in range(cfg.depth))
        self.decoder_attn = Attention(c, heads=1, head_dim=c, context_dim=c)
        self.to_logit = nn.Linear(c, 1)

    # ---- encoder ------------------------------------------------------------------------------

    def encoder_queries(self, points: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """The encoder's queries ``Q_enc`` ``(B, M, C)`` for points ``(B, N, 3)`` embedded as ``p`` ``(B, N, C)``."""
        b = points.shape[0]
        if self.cfg.query_type == "fps":
            n = points.shape[1]
            if n < self.cfg.n_latents:
                raise ValueError(f"query_type 'fps' needs at least n_latents={self.cfg.n_latents} points, got {n}")
            start = (torch.randint(0, n, (b,), device=points.device) if self.training
                     else torch.zeros(b, dtype=torch.long, device=points.device))
            idx = farthest_point_sample(points, self.cfg.n_latents, start)                     # (B, M)
            return self.embed(torch.gather(points, 1, idx[..., None].expand(-1, -1, 3)))        # (B, M, C)
        q_s = self.static_queries.expand(b, -1, -1)                                            # (B, M, C)
        if self.cfg.query_type == "static":
            return q_s
        q_d = self.dynamic_queries.expand(b, -1, -1)                                           # (B, M, C)
        q_d = drop_path(self.query_attn(q_d, p), self.cfg.drop_path, self.training)             # (B, M, C)
        return self.query_proj(q_s + q_d)                                                      # (B, M, C)

    def encode(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The posterior of each frame's latents.

        Parameters
        ----------
        points : torch.Tensor, ``(B, N, 3)``
            LiDAR points normalised to ``[-1, 1]``.

        Returns
        -------
        mean, logvar : torch.Tensor, ``(B, M, D)``
            ``mu`` and ``log sigma^2``, the latter clamped to :data:`LOGVAR_RANGE`.
        """
        _check_points(points, "points")
        p = self.embed(points)                                       # (B, N, C)
        x = self.encoder_queries(points, p)                          # (B, M, C)
        x = x + self.encoder_attn(x, p)                              # (B, M, C)
        x = x + self.encoder_ff(x)                                   # (B, M, C)
        mean = self.to_mean(x)                                       # (B, M, D)
        logvar = self.to_logvar(x).clamp(*LOGVAR_RANGE)              # (B, M, D)
        return mean, logvar

    @staticmethod
    def sample(mean: torch.Tensor, logvar: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """``z = mu + exp(log sigma^2 / 2) * eps`` ``(B, M, D)``; ``eps`` is ``noise`` or drawn from N(0, I)."""
        if noise is None:
            noise = torch.randn_like(mean)
        return mean + torch.exp(0.5 * logvar) * noise

    # ---- decoder ------------------------------------------------------------------------------

    def latent_tokens(self, latents: torch.Tensor) -> torch.Tensor:
        """The latent transformer: latents ``(B, M, D)`` -> tokens ``(B, M, C)`` the queries attend to.

        Run it once per frame and :meth:`occupancy_logits` on as many query chunks as needed.
        """
        x = self.from_latents(latents)                               # (B, M, C)
        for block in self.blocks:
            x = block(x)                                             # (B, M, C)
        return x

    def occupancy_logits(self, tokens: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
        """Occupancy logits ``(B, Q)`` of queries ``(B, Q, 3)`` against the tokens ``(B, M, C)`` of
        :meth:`latent_tokens`."""
        _check_points(queries, "queries")
        if queries.shape[0] != tokens.shape[0]:
            raise ValueError(f"queries hold {queries.shape[0]} frames but the latents {tokens.shape[0]}")
        q = self.embed(queries)                                      # (B, Q, C)
        return self.to_logit(self.decoder_attn(q, tokens)).squeeze(-1)   # (B, Q)

    def folded_decoder(self, tokens: torch.Tensor) -> "FoldedDecoder":
        """:meth:`occupancy_logits` for these tokens ``(B, M, C)``, folded into a few per-frame
        matrices (:class:`FoldedDecoder`): the same logits to float32 rounding, about 35 times
        fewer FLOPs a query at paper size. Build it once per frame, call it on every query chunk."""
        return FoldedDecoder(self, tokens)

    def decode(self, latents: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
        """Occupancy logits ``(B, Q)`` of queries ``(B, Q, 3)`` given latents ``(B, M, D)``."""
        if latents.ndim != 3 or latents.shape[1:] != (self.cfg.n_latents, self.cfg.latent_dim):
            raise ValueError(f"latents must have shape (B, {self.cfg.n_latents}, {self.cfg.latent_dim}), "
                             f"got {tuple(latents.shape)}")
        return self.occupancy_logits(self.latent_tokens(latents), queries)

    # ---- both ---------------------------------------------------------------------------------

    def forward(self, points: torch.Tensor, queries: torch.Tensor,
                noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode, sample, decode.

        Parameters
        ----------
        points : torch.Tensor, ``(B, N, 3)``
            LiDAR points normalised to ``[-1, 1]``.
        queries : torch.Tensor, ``(B, Q, 3)``
            Query points in the same coordinates.
        noise : torch.Tensor, ``(B, M, D)``, optional
            ``eps`` of the posterior sample. Default: drawn from N(0, I) while training, zero in
            evaluation (the posterior mean). (The official code samples in evaluation too; pass its
            ``eps`` to reproduce it.)

        Returns
        -------
        logits : torch.Tensor, ``(B, Q)``
        kl : torch.Tensor, ``(B,)``
            :func:`kl_divergence` of each frame's posterior.
        """
        mean, logvar = self.encode(points)                           # (B, M, D) each
        if noise is None and not self.training:
            noise = torch.zeros_like(mean)
        z = self.sample(mean, logvar, noise)                         # (B, M, D)
        return self.decode(z, queries), kl_divergence(mean, logvar)

    def loss(self, logits: torch.Tensor, occupied: torch.Tensor, kl: torch.Tensor) -> torch.Tensor:
        """The training loss: ``occupancy_loss(logits, occupied) + kl_weight * mean_b KL_b`` with the
        config's weights (a scalar)."""
        return (occupancy_loss(logits, occupied, self.cfg.occupied_weight, self.cfg.empty_weight)
                + self.cfg.kl_weight * kl.mean())


# ----------------------------------------------------------------------------------------------
# Layers
# ----------------------------------------------------------------------------------------------

class FourierEmbedding(nn.Module):
    """``p (..., 3) -> W [sin(pi 2^k p_a), cos(pi 2^k p_a), p] + b`` ``(..., C)``.

    The features are ordered sines (axis-major: x at ``k = 0..F-1``, then y, then z), cosines in the
    same order, then ``p`` itself.
    """

    def __init__(self, n_freqs: int, width: int):
        super().__init__()
        self.n_freqs = n_freqs
        self.proj = nn.Linear(6 * n_freqs + 3, width)

    def features(self, p: torch.Tensor) -> torch.Tensor:
        """The Fourier features ``[sin(pi 2^k p_a), cos(pi 2^k p_a), p]`` ``(..., 6F + 3)`` before the projection."""
        k = torch.arange(self.n_freqs, device=p.device, dtype=torch.float64)
        freqs = (math.pi * 2.0 ** k).to(p.dtype)                             # (F,)
        angles = (p[..., :, None] * freqs).flatten(-2)                       # (..., 3F)
        return torch.cat([angles.sin(), angles.cos(), p], dim=-1)           # (..., 6F + 3)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return self.proj(self.features(p))                                   # (..., C)


class FoldedDecoder:
    """The decoder of :meth:`VecSetAutoencoder.occupancy_logits` for fixed latent tokens, its linear
    maps multiplied out once per frame.

    For a query with Fourier features ``f`` (:meth:`FourierEmbedding.features`, ``F' = 6F + 3``)
    and the tokens ``t_j`` (``j = 1..M``) the decoder computes, with one head of width ``d``::

        e   = W_e f + b_e                                     the query's embedding (C)
        h   = gamma (e - mean(e)) / sigma + beta,  sigma = sqrt(var(e) + eps)     LayerNorm
        k_j = W_k LN_c(t_j),   v_j = W_v LN_c(t_j)            keys and values (d)
        s_j = (W_q h) . k_j / sqrt(d)                         scores
        l   = w . (W_o sum_j softmax(s)_j v_j + b_o) + b      the logit

    Everything but ``1 / sigma`` and the softmax is linear, so with ``W_c, b_c`` the embedding's
    weight and bias less their mean over the ``C`` outputs (``e - mean(e) = W_c f + b_c``) and
    ``K~ = K W_q / sqrt(d)`` ``(M, C)``::

        s     = (f A + a) / sigma + c,   A = W_c^T (gamma * K~)^T,  a = (gamma * K~) b_c,  c = K~ beta
        sigma = sqrt(|W_c f + b_c|^2 / C + eps)
        l     = sum_j exp(s_j - max s) u_j / sum_j exp(s_j - max s) + b0,   u = V W_o^T w,  b0 = w . b_o + b

    (numerator and denominator in one product with ``[u, 1]``).

    ``A``, ``a``, ``c``, ``u``, ``b0`` and the Gram matrix ``G = [W_c b_c]^T [W_c b_c] / C`` are
    computed once per frame (in float64 where the device has it, then ``A``, ``a``, ``c``, ``u``,
    ``b0`` rounded once to the model's dtype), so a query costs ``(F' + 1) M`` multiply-adds for
    the scores, ``(F' + 1)^2`` in float64 for ``sigma^2 = [f, 1] G [f, 1]^T + eps`` (float64: the
    quadratic form's terms may cancel), ``M`` exponentials and ``M`` multiply-adds, against
    ``F' C + 2 C d + 2 M d`` for the unfolded decoder (about 30,000 against 1,075,000 at paper
    size, ``C = d = M = 512``). The logits are the same function; float32
    rounds them differently, by about the float32 error of either (a query whose logit lies
    within that of 0 can change sides).
    """

    def __init__(self, ae: "VecSetAutoencoder", tokens: torch.Tensor):
        attn, c = ae.decoder_attn, ae.cfg.width
        if attn.heads != 1 or attn.norm_context is None:
            raise ValueError("FoldedDecoder: the decoder's cross-attention must have one head and a context norm")
        if tokens.ndim != 3 or tokens.shape[2] != c:
            raise ValueError(f"FoldedDecoder: tokens must be (B, M, {c}), got {tuple(tokens.shape)}")
        dt = torch.float32 if tokens.device.type == "mps" else torch.float64      # MPS has no float64
        w = lambda t: t.detach().to(dt)                                          # noqa: E731
        ln_c = attn.norm_context
        t = F.layer_norm(w(tokens), (c,), w(ln_c.weight), w(ln_c.bias), ln_c.eps)   # (B, M, C)
        w_k, w_v = w(attn.to_kv.weight).chunk(2, dim=0)                         # (d, C) each
        k_tilde = (t @ w_k.T) @ w(attn.to_q.weight) / math.sqrt(w_k.shape[0])    # (B, M, C)
        v = t @ w_v.T                                                            # (B, M, d)
        g = k_tilde * w(attn.norm.weight)                                        # (B, M, C): gamma * K~
        w_e, b_e = w(ae.embed.proj.weight), w(ae.embed.proj.bias)                # (C, F'), (C,)
        w_cen, b_cen = w_e - w_e.mean(0), b_e - b_e.mean()                       # centred over the C outputs
        a_mat = w_cen.T @ g.transpose(1, 2)                                      # (B, F', M)
        a_vec = g @ b_cen                                                        # (B, M)
        w_l = w(ae.to_logit.weight)[0]                                           # (C,)
        self.embed = ae.embed
        self.eps, self.dtype = attn.norm.eps, tokens.dtype
        # f~ = [f, 1]: the biases as one more row of the matrices
        self.weight = torch.cat((a_mat, a_vec[:, None]), dim=1).to(tokens.dtype)               # (B, F' + 1, M)
        w_aug = torch.cat((w_cen, b_cen[:, None]), dim=1)                                      # (C, F' + 1)
        self.gram = (w_aug.T @ w_aug / c).to(dt)                                               # (F' + 1, F' + 1)
        self.c = (k_tilde @ w(attn.norm.bias))[:, None].to(tokens.dtype)                       # (B, 1, M)
        u = v @ (w(attn.to_out.weight).T @ w_l)                                                # (B, M)
        self.u_one = torch.stack((u, torch.ones_like(u)), dim=2).to(tokens.dtype)             # (B, M, 2): [u, 1]
        self.b0 = (w_l @ w(attn.to_out.bias) + w(ae.to_logit.bias)[0]).to(tokens.dtype)       # ()

    @torch.no_grad()
    def __call__(self, queries: torch.Tensor) -> torch.Tensor:
        """Occupancy logits ``(B, Q)`` of queries ``(B, Q, 3)`` (:meth:`VecSetAutoencoder.occupancy_logits`)."""
        _check_points(queries, "queries")
        if queries.shape[0] != self.weight.shape[0]:
            raise ValueError(f"queries hold {queries.shape[0]} frames but the latents {self.weight.shape[0]}")
        f = self.embed.features(queries.to(self.dtype))                                       # (B, Q, F')
        f = torch.cat((f, f.new_ones(f.shape[:2] + (1,))), dim=2)                              # (B, Q, F' + 1)
        # sigma^2 = |W_c f + b_c|^2 / C + eps, from the Gram matrix in float64 (no (Q, C) embedding made)
        f64 = f.to(self.gram.dtype)
        var = ((f64 @ self.gram) * f64).sum(dim=2, keepdim=True)                               # (B, Q, 1)
        sigma = (var + self.eps).sqrt().to(self.dtype)
        t = torch.bmm(f, self.weight)                                                          # (B, Q, M): f A + a
        s = torch.addcdiv(self.c, t, sigma, out=t)                                             # (B, Q, M) scores
        s = s.sub_(s.amax(dim=2, keepdim=True)).exp_()                                         # exp(s - max s)
        num_den = s @ self.u_one                                                               # (B, Q, 2)
        return num_den[..., 0] / num_den[..., 1] + self.b0                                    # (B, Q)


class Attention(nn.Module):
    """Pre-norm multi-head attention ``to_out(softmax(q k^T / sqrt(d)) v)``, no residual.

    ``q = to_q(LN(x))``; keys and values ``to_kv(c)`` come from ``c = LN(x)`` (self-attention, no
    context), ``LN_c(context)`` (cross-attention, ``norm_context``) or the raw context.
    """

    def __init__(self, dim: int, *, heads: int, head_dim: int, context_dim: int | None = None,
                 norm_context: bool = True):
        super().__init__()
        inner = heads * head_dim
        self.heads = heads
        self.norm = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(context_dim) if context_dim is not None and norm_context else None
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_kv = nn.Linear(context_dim or dim, 2 * inner, bias=False)
        self.to_out = nn.Linear(inner, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        h = self.norm(x)                                                     # (B, L, C)
        if context is None:
            context = h
        elif self.norm_context is not None:
            context = self.norm_context(context)                             # (B, S, C_ctx)
        q = self.to_q(h)                                                     # (B, L, H d)
        k, v = self.to_kv(context).chunk(2, dim=-1)                          # (B, S, H d) each
        q, k, v = (t.unflatten(-1, (self.heads, -1)).transpose(1, 2) for t in (q, k, v))   # (B, H, ., d)
        out = F.scaled_dot_product_attention(q, k, v)                        # (B, H, L, d)
        return self.to_out(out.transpose(1, 2).flatten(-2))                  # (B, L, C)


class FeedForward(nn.Module):
    """Pre-norm GEGLU feed-forward ``fc2(a * GELU(g))`` with ``[a, g] = fc1(LN(x))``, no residual."""

    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.fc1 = nn.Linear(dim, 2 * mult * dim)
        self.fc2 = nn.Linear(mult * dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, g = self.fc1(self.norm(x)).chunk(2, dim=-1)                       # (B, L, mult C) each
        return self.fc2(a * F.gelu(g))                                       # (B, L, C)


class LatentBlock(nn.Module):
    """One block of the latent transformer: ``x + DP(Attn(x))``, then ``+ DP(FF(.))``, DP stochastic depth."""

    def __init__(self, cfg: VecSetAEConfig):
        super().__init__()
        self.drop = cfg.drop_path
        self.attn = Attention(cfg.width, heads=cfg.heads, head_dim=cfg.head_dim)
        self.ff = FeedForward(cfg.width, cfg.ff_mult)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + drop_path(self.attn(x), self.drop, self.training)            # (B, M, C)
        return x + drop_path(self.ff(x), self.drop, self.training)           # (B, M, C)


def drop_path(x: torch.Tensor, rate: float, training: bool) -> torch.Tensor:
    """Stochastic depth: while training, zero the whole of ``x`` for a frame with probability
    ``rate`` and scale the kept frames by ``1 / (1 - rate)``; the identity otherwise."""
    if not training or rate == 0.0:
        return x
    keep = torch.rand((x.shape[0],) + (1,) * (x.ndim - 1), device=x.device, dtype=x.dtype) >= rate
    return x * keep.to(x.dtype) / (1.0 - rate)


def farthest_point_sample(points: torch.Tensor, m: int, start: torch.Tensor) -> torch.Tensor:
    """Indices ``(B, m)`` of ``m`` points of each cloud ``(B, N, 3)`` chosen by farthest point sampling.

    The first index is ``start`` ``(B,)``; each next one is the point farthest (Euclidean) from
    those already chosen (the first such index on ties).
    """
    b, n, _ = points.shape
    if not 1 <= m <= n:
        raise ValueError(f"farthest_point_sample: m must be in [1, {n}], got {m}")
    with torch.no_grad():
        idx = torch.empty(b, m, dtype=torch.long, device=points.device)
        dist = torch.full((b, n), math.inf, dtype=points.dtype, device=points.device)   # (B, N)
        cur = start.to(torch.long)                                                        # (B,)
        rows = torch.arange(b, device=points.device)
        for i in range(m):
            idx[:, i] = cur
            d = ((points - points[rows, cur][:, None]) ** 2).sum(-1)                      # (B, N)
            dist = torch.minimum(dist, d)
            cur = dist.argmax(-1)
    return idx


def _check_points(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"{name} must be a (B, N, 3) tensor, got "
                         f"{tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__}")
    if x.shape[1] == 0:
        raise ValueError(f"{name} must hold at least one point per frame, got shape {tuple(x.shape)}")


# ----------------------------------------------------------------------------------------------
# Losses
# ----------------------------------------------------------------------------------------------

def occupancy_loss(logits: torch.Tensor, occupied: torch.Tensor, occupied_weight: float = 0.1,
                   empty_weight: float = 1.0) -> torch.Tensor:
    """Weighted binary cross-entropy of the occupancy logits (RaLD's training loss).

    .. math::

        L = w_o \\frac{1}{|O|} \\sum_{q \\in O} \\log(1 + e^{-\\ell_q})
          + w_e \\frac{1}{|E|} \\sum_{q \\in E} \\log(1 + e^{\\ell_q})

    over the occupied queries ``O`` and the empty ones ``E`` of the whole batch (each mean over its
    own queries, as the official code's two ``BCEWithLogitsLoss`` terms); a set with no query adds 0.

    Parameters
    ----------
    logits : torch.Tensor, ``(B, Q)``
    occupied : torch.Tensor, bool or 0/1, ``(B, Q)``
        The labels.
    occupied_weight, empty_weight : float
        ``w_o`` and ``w_e`` (RaLD: 0.1 and 1.0).

    Returns
    -------
    torch.Tensor
        The scalar loss.
    """
    if occupied.shape != logits.shape:
        raise ValueError(f"occupied {tuple(occupied.shape)} must have the shape of logits {tuple(logits.shape)}")
    occ = occupied.to(torch.bool)
    bce = F.binary_cross_entropy_with_logits(logits, occ.to(logits.dtype), reduction="none")   # (B, Q)
    zero = bce.new_zeros(())
    n_occ, n_emp = occ.sum(), (~occ).sum()
    l_occ = torch.where(occ, bce, zero).sum() / n_occ.clamp_min(1)
    l_emp = torch.where(occ, zero, bce).sum() / n_emp.clamp_min(1)
    return occupied_weight * l_occ + empty_weight * l_emp


def kl_divergence(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """``KL(N(mu, sigma^2) || N(0, I))`` per frame, averaged over the latent entries ``(B,)``.

    .. math::

        \\mathrm{KL}_b = \\frac{1}{2 M D} \\sum_{m, d} \\left(\\mu_{bmd}^2 + \\sigma_{bmd}^2 - 1
        - \\log \\sigma_{bmd}^2\\right)

    (the mean, not the sum, over the ``M x D`` entries, as the official code; the loss takes its
    mean over the batch).
    """
    return 0.5 * (mean.square() + logvar.exp() - 1.0 - logvar).flatten(1).mean(1)


# ----------------------------------------------------------------------------------------------
# Size variants
# ----------------------------------------------------------------------------------------------

def rald_ae(**overrides) -> VecSetAutoencoder:
    """RaLD's LiDAR autoencoder at the official size (``kl_d512_m512_l32_mix``): hybrid queries,
    512 latents of 32, a 24-block decoder of width 512 (108,002,881 parameters)."""
    return VecSetAutoencoder(VecSetAEConfig(**overrides))


def rald_ae_s(**overrides) -> VecSetAutoencoder:
    """RaLD's autoencoder, small: width 128, 4 blocks, 128 latents of 32; trains on 2 CPU cores."""
    cfg = dict(width=128, depth=4, heads=4, head_dim=32, n_latents=128, latent_dim=32)
    return VecSetAutoencoder(VecSetAEConfig(**{**cfg, **overrides}))


def rald_ae_tiny(**overrides) -> VecSetAutoencoder:
    """RaLD's autoencoder, tiny (tests): width 64, 2 blocks, 32 latents of 8, no stochastic depth."""
    cfg = dict(width=64, depth=2, heads=2, head_dim=32, n_latents=32, latent_dim=8, drop_path=0.0)
    return VecSetAutoencoder(VecSetAEConfig(**{**cfg, **overrides}))
