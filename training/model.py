"""VecSet backbone and the Controllable VAE (C-VAE) of Sec. 3.3.

The backbone follows 3DShape2VecSet / Hunyuan3D-2.1's shape VAE, in small named parts:

- :class:`FourierEmbedder`: parameter-free Fourier features of 3D points, shared by encoder and decoder.
- :class:`Attention` / :class:`AttentionBlock`: one attention class for self- and cross-attention.
- :func:`farthest_point_sample` (:mod:`vnc_warp.sampling`, one Warp kernel launch): picks the M latent queries
  among the surface points.
- :class:`PointEncoder`: the latent queries cross-attend to the embedded surface, then self-attend.
- :class:`KLBottleneck` / :class:`DiagonalGaussian`: ``pre`` (width -> mean, logvar), ``post`` (latent -> width).
- :class:`LatentDecoder`: self-attention latent transformer plus a chunked cross-attention query
  decoder predicting the truncated SDF, output head zero-initialised.
- :class:`TimeEmbedding`: normalised evolution time t in [0, 1] (Eq. (7)) -> a few time tokens.

Models (all offer ``encode``, ``decode``; ``forward`` composes them):

- :class:`VecSetVAE`: the plain VecSet VAE.
- :class:`CVAE1`: C-VAE-I, the encoder's intermediate features cross-attend to the time tokens.
- :class:`CVAE2`: C-VAE-II, a frozen pre-trained :class:`VecSetVAE` encoder; its latent codes z_geo
  cross-attend to the time tokens (latent code modulation); only attention modules and decoder train.

Coordinates are normalised (inside [-1, 1]^3, see :mod:`vnc_warp.training.inference`); the SDF is
in the same units, negative inside.
"""

from __future__ import annotations

import abc
import copy
import math
import os

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

from vnc_warp.sampling import farthest_point_sample

from .checkpoint import CheckpointError, load_checkpoint
from .config import ModelConfig, TrainConfig

__all__ = [
    "farthest_point_sample",
    "FourierEmbedder",
    "Attention",
    "FeedForward",
    "AttentionBlock",
    "TimeEmbedding",
    "timestep_embedding",
    "PointEncoder",
    "DiagonalGaussian",
    "KLBottleneck",
    "QueryDecoder",
    "LatentDecoder",
    "LatentModulator",
    "VecSetVAE",
    "CVAE1",
    "CVAE2",
    "build_model",
    "load_model",
]


def _gather_tokens(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """(B, N, C) x (B, M) -> (B, M, C)."""
    return torch.gather(x, 1, idx.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


class FourierEmbedder(nn.Module):
    """Fourier features ``(x, sin(f_k x), cos(f_k x))`` with ``f_k = 2^k`` (times pi if ``include_pi``).

    Parameter-free, so one instance is shared by the encoder and the decoder.

    Attributes:
        out_dim: 3 * (2 * num_freqs + 1) features per point.
    """

    def __init__(self, *, num_freqs: int = 8, include_pi: bool = False) -> None:
        super().__init__()
        freqs = 2.0 ** torch.arange(num_freqs, dtype=torch.float32)
        if include_pi:
            freqs = freqs * math.pi
        self.register_buffer("freqs", freqs, persistent=False)
        self.out_dim = 3 * (2 * num_freqs + 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) positions -> (..., out_dim) features."""
        xf = (x.unsqueeze(-1) * self.freqs).flatten(-2)
        return torch.cat([x, xf.sin(), xf.cos()], dim=-1)


class Attention(nn.Module):
    """Multi-head attention through ``F.scaled_dot_product_attention``.

    Self-attention when called without ``context``, cross-attention (queries from ``x``, keys and
    values from ``context``) otherwise.
    """

    def __init__(self, dim: int, *, heads: int, context_dim: int | None = None, qkv_bias: bool = False,
                 qk_norm: bool = True) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"Attention: dim ({dim}) must be a multiple of heads ({heads})")
        self.heads = heads
        head_dim = dim // heads
        self.to_q = nn.Linear(dim, dim, bias=qkv_bias)
        self.to_kv = nn.Linear(context_dim or dim, 2 * dim, bias=qkv_bias)
        self.q_norm = nn.LayerNorm(head_dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """x: (B, N, dim); context: (B, L, context_dim) or None -> (B, N, dim)."""
        ctx = x if context is None else context
        b, n, c = x.shape
        h = self.heads
        q = self.to_q(x).view(b, n, h, c // h).transpose(1, 2)
        k, v = self.to_kv(ctx).view(b, ctx.shape[1], 2, h, c // h).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(self.q_norm(q), self.k_norm(k), v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class FeedForward(nn.Module):
    """Two-layer GELU MLP, ``dim -> mlp_ratio * dim -> dim``."""

    def __init__(self, dim: int, *, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        hidden = int(dim * mlp_ratio)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class AttentionBlock(nn.Module):
    """Pre-norm residual block: ``x + Attn(LN(x), LN(ctx))`` then ``x + FF(LN(x))``.

    A self-attention block without ``context_dim``, a cross-attention block with it.
    """

    def __init__(self, dim: int, *, heads: int, context_dim: int | None = None, mlp_ratio: float = 4.0,
                 qkv_bias: bool = False, qk_norm: bool = True) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(context_dim) if context_dim else None
        self.attn = Attention(dim, heads=heads, context_dim=context_dim, qkv_bias=qkv_bias, qk_norm=qk_norm)
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = FeedForward(dim, mlp_ratio=mlp_ratio)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """x: (B, N, dim); context: (B, L, context_dim), required iff built with ``context_dim``."""
        if (context is None) != (self.norm_context is None):
            kind = "a cross-attention" if self.norm_context is not None else "a self-attention"
            how = "without" if context is None else "with"
            raise ValueError(f"AttentionBlock: {kind} block was called {how} context")
        ctx = None if context is None else self.norm_context(context)
        x = x + self.attn(self.norm(x), ctx)
        return x + self.mlp(self.norm_mlp(x))


def timestep_embedding(t: torch.Tensor, dim: int, *, scale: float = 1000.0,
                       max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal features of the normalised time: (B,) t in [0, 1] -> (B, dim) ``[cos, sin]``.

    ``t`` is scaled by ``scale`` first; the fastest feature turns ``scale`` radians per unit of t.
    """
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = (t.float() * scale).unsqueeze(-1) * freqs
    return torch.cat([args.cos(), args.sin()], dim=-1)


class TimeEmbedding(nn.Module):
    """Normalised evolution time t (Eq. (7)) -> ``num_tokens`` tokens of ``width`` channels.

    Sinusoidal features (:func:`timestep_embedding`, fastest ``scale`` radians per unit of t) pass an MLP whose
    output is split into tokens. A trajectory is seen at 9-33 values of t and decoded at any other, so the
    features must change little between neighbouring stages: at ``scale = 10`` the fastest turns 0.3 rad over a
    32-stage step, where the diffusion-style 1000 turns 31 rad and makes every unseen t a new input.
    """

    def __init__(self, width: int, *, num_tokens: int = 4, freq_dim: int = 256, scale: float = 10.0) -> None:
        super().__init__()
        self.num_tokens = num_tokens
        self.freq_dim = freq_dim
        self.scale = scale
        self.mlp = nn.Sequential(nn.Linear(freq_dim, width), nn.SiLU(), nn.Linear(width, num_tokens * width))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """(B,) float t -> (B, num_tokens, width)."""
        emb = self.mlp(timestep_embedding(t, self.freq_dim, scale=self.scale))
        return emb.view(t.shape[0], self.num_tokens, -1)


class PointEncoder(nn.Module):
    """Cross-attention point-set encoder.

    Surface points are embedded (Fourier features of xyz, concatenated with the unit normal, then a
    linear projection); ``num_latents`` of them are chosen by farthest-point sampling as queries that
    cross-attend to all embedded points; ``depth`` self-attention blocks follow. With
    ``condition_dim``, a cross-attention block to condition tokens follows the point cross-attention
    and every self-attention block: the intermediate feature fusion of C-VAE-I.
    """

    def __init__(self, *, embedder: FourierEmbedder, width: int, heads: int, num_latents: int, depth: int,
                 condition_dim: int | None = None, mlp_ratio: float = 4.0, qkv_bias: bool = False,
                 qk_norm: bool = True) -> None:
        super().__init__()
        block = dict(heads=heads, mlp_ratio=mlp_ratio, qkv_bias=qkv_bias, qk_norm=qk_norm)
        self.embedder = embedder
        self.num_latents = num_latents
        self.input_proj = nn.Linear(embedder.out_dim + 3, width)
        self.cross = AttentionBlock(width, context_dim=width, **block)
        self.layers = nn.ModuleList(AttentionBlock(width, **block) for _ in range(depth))
        self.condition = (nn.ModuleList(AttentionBlock(width, context_dim=condition_dim, **block)
                                        for _ in range(depth + 1)) if condition_dim else None)

    def identity_condition(self) -> None:
        """Make every fusion block the identity (zero output layers of both residual branches): the encoder then
        encodes as the plain encoder does at every t, until training moves them."""
        for blk in self.condition or ():
            for layer in (blk.attn.proj, blk.mlp.net[-1]):
                nn.init.zeros_(layer.weight)
                nn.init.zeros_(layer.bias)

    def forward(self, surface: torch.Tensor, *, condition: torch.Tensor | None = None,
                random_start: bool = False) -> torch.Tensor:
        """Encode a surface sample.

        Args:
            surface: (B, N, 6) float, xyz + unit normal, N >= num_latents.
            condition: (B, T, condition_dim) tokens; required iff built with ``condition_dim``.
            random_start: random first farthest-point sample (training) instead of index 0.

        Returns:
            (B, num_latents, width) latent features.
        """
        if (condition is None) != (self.condition is None):
            raise ValueError("PointEncoder: condition tokens must be given exactly when the encoder is conditioned")
        xyz = surface[..., :3]
        feats = self.input_proj(torch.cat([self.embedder(xyz), surface[..., 3:]], dim=-1))
        idx = farthest_point_sample(xyz, self.num_latents, random_start=random_start)
        x = self.cross(_gather_tokens(feats, idx), feats)
        x = self._fuse(0, x, condition)
        for i, layer in enumerate(self.layers, start=1):
            x = self._fuse(i, layer(x), condition)
        return x

    def _fuse(self, i: int, x: torch.Tensor, condition: torch.Tensor | None) -> torch.Tensor:
        return x if self.condition is None else self.condition[i](x, condition)


class DiagonalGaussian:
    """Diagonal Gaussian posterior over a latent set.

    Attributes:
        mean: (B, M, C).
        logvar: (B, M, C), clamped to [-30, 20].
    """

    def __init__(self, mean: torch.Tensor, logvar: torch.Tensor) -> None:
        self.mean = mean
        self.logvar = logvar.clamp(-30.0, 20.0)

    @property
    def std(self) -> torch.Tensor:
        return torch.exp(0.5 * self.logvar)

    def sample(self) -> torch.Tensor:
        """Reparameterised sample ``mean + std * eps`` (eps from the global torch RNG)."""
        return self.mean + self.std * torch.randn_like(self.mean)

    def kl(self, prior_logvar: torch.Tensor | float = 0.0) -> torch.Tensor:
        """(B,) KL(q || N(0, s^2 I)) with ``log s^2 = prior_logvar``, averaged over the M x C latent entries.

        Args:
            prior_logvar: scalar or (B,) log-variance of the isotropic prior per item (0: N(0, I)).
        """
        mean, logvar = self.mean.float(), self.logvar.float()
        pl = torch.as_tensor(prior_logvar, dtype=torch.float32, device=mean.device)
        pl = pl.reshape(-1, *([1] * (mean.ndim - 1))) if pl.ndim else pl
        return 0.5 * ((mean.square() + logvar.exp()) * torch.exp(-pl) - 1.0 - logvar + pl).flatten(1).mean(1)


class KLBottleneck(nn.Module):
    """KL bottleneck: ``pre`` maps features to (mean, logvar), ``post`` maps latents back to width.

    The log-variance half of ``pre`` starts at ``logvar_init`` (bias; weights zero). Training decodes a
    sample of the posterior and inference its mean: a posterior that starts at N(mean, 1) trains the decoder
    on codes an order of magnitude noisier than the ones it is evaluated on, and a small KL weight never
    shrinks it; a narrow start (std e^-4 at -8) makes both the same code from the first step, and the KL
    term then widens it only as far as the reconstruction allows.
    """

    def __init__(self, width: int, *, latent_dim: int, logvar_init: float = -8.0) -> None:
        super().__init__()
        self.pre = nn.Linear(width, 2 * latent_dim)
        self.post = nn.Linear(latent_dim, width)
        with torch.no_grad():
            self.pre.weight[latent_dim:].zero_()
            self.pre.bias[latent_dim:].fill_(logvar_init)

    def posterior(self, h: torch.Tensor) -> DiagonalGaussian:
        """(B, M, width) features -> posterior over (B, M, latent_dim) latents."""
        mean, logvar = self.pre(h).chunk(2, dim=-1)
        return DiagonalGaussian(mean, logvar)


class QueryDecoder(nn.Module):
    """Chunked cross-attention decoder: embedded query points attend to the latent tokens.

    The output head's weights are zero-initialised and its bias is ``sdf_init``, so an untrained decoder predicts
    that constant everywhere: 0 (the surface everywhere) or, e.g., the TSDF truncation (empty space, so that no
    surface exists where training never put one).
    """

    def __init__(self, *, embedder: FourierEmbedder, width: int, heads: int, chunk_size: int = 32768,
                 mlp_ratio: float = 4.0, qkv_bias: bool = False, qk_norm: bool = True, sdf_init: float = 0.0) -> None:
        super().__init__()
        self.embedder = embedder
        self.chunk_size = chunk_size
        self.query_proj = nn.Linear(embedder.out_dim, width)
        self.cross = AttentionBlock(width, heads=heads, context_dim=width, mlp_ratio=mlp_ratio,
                                    qkv_bias=qkv_bias, qk_norm=qk_norm)
        self.norm = nn.LayerNorm(width)
        self.head = nn.Linear(width, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.constant_(self.head.bias, sdf_init)

    def forward(self, tokens: torch.Tensor, queries: torch.Tensor, *, chunk_size: int | None = None) -> torch.Tensor:
        """tokens: (B, M, width); queries: (B, Q, 3) -> (B, Q) predicted truncated SDF."""
        chunk = chunk_size or self.chunk_size
        out = [self._decode(tokens, q) for q in queries.split(chunk, dim=1)]
        return torch.cat(out, dim=1)

    def _decode(self, tokens: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
        if queries.requires_grad and torch.is_grad_enabled():
            # The eikonal term differentiates the SDF gradient w.r.t. the queries once more; the fused
            # SDPA kernels (flash, memory-efficient) have no double backward, the math one has.
            with sdpa_kernel(SDPBackend.MATH):
                x = self.cross(self.query_proj(self.embedder(queries)), tokens)
        else:
            x = self.cross(self.query_proj(self.embedder(queries)), tokens)
        # The SDF head runs in float32 even under bf16 autocast: bf16 keeps 8 mantissa bits, too coarse
        # for truncated-SDF targets whose near-surface values are a few thousandths.
        with torch.autocast(device_type=x.device.type, enabled=False):
            return self.head(self.norm(x.float())).squeeze(-1)


class LatentDecoder(nn.Module):
    """Self-attention latent transformer followed by the :class:`QueryDecoder`."""

    def __init__(self, *, embedder: FourierEmbedder, width: int, heads: int, depth: int, chunk_size: int = 32768,
                 mlp_ratio: float = 4.0, qkv_bias: bool = False, qk_norm: bool = True, sdf_init: float = 0.0) -> None:
        super().__init__()
        block = dict(heads=heads, mlp_ratio=mlp_ratio, qkv_bias=qkv_bias, qk_norm=qk_norm)
        self.layers = nn.ModuleList(AttentionBlock(width, **block) for _ in range(depth))
        self.queries = QueryDecoder(embedder=embedder, width=width, chunk_size=chunk_size, sdf_init=sdf_init, **block)

    def tokens(self, h: torch.Tensor) -> torch.Tensor:
        """(B, M, width) post-projected latents -> (B, M, width) tokens for the query decoder."""
        for layer in self.layers:
            h = layer(h)
        return h

    def forward(self, h: torch.Tensor, queries: torch.Tensor, *, chunk_size: int | None = None) -> torch.Tensor:
        """(B, M, width), (B, Q, 3) -> (B, Q) SDF."""
        return self.queries(self.tokens(h), queries, chunk_size=chunk_size)


class LatentModulator(nn.Module):
    """C-VAE-II latent code modulation: z_geo cross-attends to time tokens.

    The latent codes (posterior mean of the frozen encoder, (B, M, C)) are projected to ``width``,
    pass ``depth`` cross-attention blocks whose context is the time tokens, and a projection outputs a
    residual shift of the mean (zero-initialised: z_ctl starts at z_geo) and the log-variance of z_ctl
    itself (starting at ``logvar_init``). The frozen encoder's log-variance is not inherited: z_ctl is a
    new code whose spread the C-VAE-II objective sets, and a frozen spread near 1 would train the decoder
    on noise while inference decodes the mean (see :class:`KLBottleneck`).
    """

    def __init__(self, *, latent_dim: int, width: int, heads: int, depth: int, mlp_ratio: float = 4.0,
                 qkv_bias: bool = False, qk_norm: bool = True, logvar_init: float = -8.0) -> None:
        super().__init__()
        self.proj_in = nn.Linear(latent_dim, width)
        self.blocks = nn.ModuleList(AttentionBlock(width, heads=heads, context_dim=width, mlp_ratio=mlp_ratio,
                                                   qkv_bias=qkv_bias, qk_norm=qk_norm) for _ in range(depth))
        self.norm = nn.LayerNorm(width)
        self.proj_out = nn.Linear(width, 2 * latent_dim)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)
        with torch.no_grad():
            self.proj_out.bias[latent_dim:].fill_(logvar_init)

    def forward(self, prior: DiagonalGaussian, time_tokens: torch.Tensor) -> DiagonalGaussian:
        """Frozen posterior and (B, T, width) time tokens -> time-modulated posterior z_ctl."""
        x = self.proj_in(prior.mean)
        for block in self.blocks:
            x = block(x, time_tokens)
        d_mean, logvar = self.proj_out(self.norm(x)).chunk(2, dim=-1)
        return DiagonalGaussian(prior.mean + d_mean, logvar)


def _batch_time(t: torch.Tensor | float | None, batch: int, device: torch.device) -> torch.Tensor:
    if t is None:
        raise ValueError("this model is time-conditioned: pass t, the normalised evolution time in [0, 1]")
    t = torch.as_tensor(t, dtype=torch.float32, device=device)
    if t.ndim == 0:
        t = t.expand(batch)
    if t.shape != (batch,):
        raise ValueError(f"t must be a scalar or ({batch},), got {tuple(t.shape)}")
    return t


def _check_inputs(surface: torch.Tensor | None, queries: torch.Tensor | None) -> None:
    if surface is not None and (surface.ndim != 3 or surface.shape[-1] != 6):
        raise ValueError(f"surface must be (B, N, 6) xyz + normal, got {tuple(surface.shape)}")
    if queries is not None and (queries.ndim != 3 or queries.shape[-1] != 3):
        raise ValueError(f"queries must be (B, Q, 3), got {tuple(queries.shape)}")


class _LatentSetModel(nn.Module, abc.ABC):
    """``decode`` and ``forward`` shared by the three models; subclasses define ``encode`` and ``latent_tokens``."""

    time_conditioned: bool = False
    decoder: LatentDecoder

    @abc.abstractmethod
    def encode(self, surface: torch.Tensor, t: torch.Tensor | float | None = None, *,
               sample: bool | None = None) -> tuple[torch.Tensor, DiagonalGaussian]:
        """``(z, posterior)`` of a (B, N, 6) surface sample at time t."""

    @abc.abstractmethod
    def latent_tokens(self, z: torch.Tensor) -> torch.Tensor:
        """(B, M, latent_dim) latents -> (B, M, width) tokens for the query decoder."""

    def decode(self, z: torch.Tensor, queries: torch.Tensor, *, chunk_size: int | None = None) -> torch.Tensor:
        """Predicted truncated SDF.

        Args:
            z: (B, M, latent_dim) latents from :meth:`encode`.
            queries: (B, Q, 3) normalised query points.
            chunk_size: queries per cross-attention chunk (default: the model's).

        Returns:
            (B, Q) SDF, normalised units, negative inside.
        """
        _check_inputs(None, queries)
        return self.decoder.queries(self.latent_tokens(z), queries, chunk_size=chunk_size)

    def forward(self, surface: torch.Tensor, queries: torch.Tensor, t: torch.Tensor | float | None = None, *,
                eikonal_queries: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Encode ``surface`` (at time ``t``) and decode the SDF at ``queries``.

        Args:
            surface: (B, N, 6) xyz + unit normal.
            queries: (B, Q, 3).
            t: (B,) or scalar normalised time; required by the C-VAEs, ignored by the plain VAE.
            eikonal_queries: (B, E, 3) points with ``requires_grad=True`` whose SDF is also decoded,
                for the eikonal term (a separate, smaller set keeps its double backward cheap).

        Returns:
            ``{"tsdf": (B, Q), "z": (B, M, latent_dim), "mean", "logvar"}`` (the posterior, (B, M, latent_dim)
            each; the loss takes its KL), plus ``"eikonal_tsdf"``: (B, E) when ``eikonal_queries`` is given.
        """
        _check_inputs(surface, queries)
        z, posterior = self.encode(surface, t)
        tokens = self.latent_tokens(z)
        out = {"tsdf": self.decoder.queries(tokens, queries), "z": z, "mean": posterior.mean,
               "logvar": posterior.logvar}
        if eikonal_queries is not None:
            _check_inputs(None, eikonal_queries)
            out["eikonal_tsdf"] = self.decoder.queries(tokens, eikonal_queries)
        return out


class VecSetVAE(_LatentSetModel):
    """The plain VecSet VAE (3DShape2VecSet); with ``time_tokens > 0`` it is C-VAE-I (see :class:`CVAE1`).

    Args:
        width: token width.
        heads: attention heads.
        num_latents: latent tokens M.
        latent_dim: channels per latent token.
        encoder_depth: encoder self-attention blocks.
        decoder_depth: latent transformer blocks.
        num_freqs: Fourier octaves.
        include_pi: Fourier frequencies times pi.
        mlp_ratio: feed-forward expansion.
        qkv_bias: bias in q/k/v projections.
        qk_norm: per-head LayerNorm on q and k.
        chunk_size: queries per decoder chunk.
        time_tokens: 0 for the plain VAE; > 0 adds the time embedding and the encoder's time
            cross-attention blocks.
        time_freq_dim: sinusoidal time feature width.
        time_scale: radians per unit of t of the fastest time feature (see :class:`TimeEmbedding`).
        logvar_init: initial log-variance of the posterior (see :class:`KLBottleneck`).
        sdf_init: SDF an untrained decoder predicts everywhere (see :class:`QueryDecoder`).
    """

    def __init__(self, *, width: int, heads: int, num_latents: int, latent_dim: int, encoder_depth: int,
                 decoder_depth: int, num_freqs: int = 8, include_pi: bool = False, mlp_ratio: float = 4.0,
                 qkv_bias: bool = False, qk_norm: bool = True, chunk_size: int = 32768, time_tokens: int = 0,
                 time_freq_dim: int = 256, time_scale: float = 10.0, logvar_init: float = -8.0,
                 sdf_init: float = 0.0) -> None:
        super().__init__()
        block = dict(mlp_ratio=mlp_ratio, qkv_bias=qkv_bias, qk_norm=qk_norm)
        self.num_latents = num_latents
        self.latent_dim = latent_dim
        self.time_conditioned = time_tokens > 0
        self.embedder = FourierEmbedder(num_freqs=num_freqs, include_pi=include_pi)
        self.time_embed = (TimeEmbedding(width, num_tokens=time_tokens, freq_dim=time_freq_dim, scale=time_scale)
                           if self.time_conditioned else None)
        self.encoder = PointEncoder(embedder=self.embedder, width=width, heads=heads, num_latents=num_latents,
                                    depth=encoder_depth, condition_dim=width if self.time_conditioned else None,
                                    **block)
        self.bottleneck = KLBottleneck(width, latent_dim=latent_dim, logvar_init=logvar_init)
        self.decoder = LatentDecoder(embedder=self.embedder, width=width, heads=heads, depth=decoder_depth,
                                     chunk_size=chunk_size, sdf_init=sdf_init, **block)

    def posterior(self, surface: torch.Tensor, t: torch.Tensor | float | None = None, *,
                  random_start: bool = False) -> DiagonalGaussian:
        """Posterior q(z | surface[, t]) over (B, M, latent_dim) latents."""
        _check_inputs(surface, None)
        condition = None
        if self.time_embed is not None:
            condition = self.time_embed(_batch_time(t, surface.shape[0], surface.device))
        h = self.encoder(surface, condition=condition, random_start=random_start)
        return self.bottleneck.posterior(h)

    def encode(self, surface: torch.Tensor, t: torch.Tensor | float | None = None, *,
               sample: bool | None = None) -> tuple[torch.Tensor, DiagonalGaussian]:
        """Latents of a surface sample.

        Args:
            surface: (B, N, 6) xyz + unit normal.
            t: normalised time, (B,) or scalar; required iff time-conditioned.
            sample: draw from the posterior (default: in training mode) instead of taking its mean;
                in training mode the first farthest-point sample is random too.

        Returns:
            ``(z, posterior)``, z: (B, M, latent_dim).
        """
        sample = self.training if sample is None else sample
        post = self.posterior(surface, t, random_start=self.training)
        return (post.sample() if sample else post.mean), post

    def latent_tokens(self, z: torch.Tensor) -> torch.Tensor:
        """(B, M, latent_dim) -> (B, M, width) decoder tokens (``post`` + latent transformer)."""
        return self.decoder.tokens(self.bottleneck.post(z))


class CVAE1(VecSetVAE):
    """C-VAE-I, intermediate feature fusion (Sec. 3.3, Fig. 4): the encoder's features after the point
    cross-attention and after each self-attention block cross-attend to the time tokens of t.

    Takes the :class:`VecSetVAE` arguments; ``time_tokens`` must be >= 1.
    """

    def __init__(self, *, time_tokens: int = 4, time_freq_dim: int = 256, time_scale: float = 10.0, **backbone) -> None:
        if time_tokens < 1:
            raise ValueError(f"CVAE1: time_tokens must be >= 1, got {time_tokens}")
        super().__init__(time_tokens=time_tokens, time_freq_dim=time_freq_dim, time_scale=time_scale, **backbone)


class CVAE2(_LatentSetModel):
    """C-VAE-II, latent code modulation (Sec. 3.3, Fig. 4).

    The encoder of a pre-trained plain :class:`VecSetVAE` is frozen (no gradients, eval mode, a
    deterministic farthest-point start) and yields the posterior of z_geo; a :class:`LatentModulator`
    lets z_geo cross-attend to the time tokens and outputs z_ctl. Trainable: the time embedding, the
    modulator and a copy of the pre-trained decoder (``post`` and :class:`LatentDecoder`).

    Args:
        base: the pre-trained plain VAE (not time-conditioned); its decoder is copied, its encoder frozen.
        time_tokens: time tokens.
        time_freq_dim: sinusoidal time feature width.
        time_scale: radians per unit of t of the fastest time feature (see :class:`TimeEmbedding`).
        modulator_depth: cross-attention blocks of the modulator.
        heads: heads of the modulator (default: those of the base encoder).
        logvar_init: initial log-variance of z_ctl (see :class:`LatentModulator`).
    """

    time_conditioned = True

    def __init__(self, *, base: VecSetVAE, time_tokens: int = 4, time_freq_dim: int = 256, time_scale: float = 10.0,
                 modulator_depth: int = 2, heads: int | None = None, logvar_init: float = -8.0) -> None:
        super().__init__()
        if not isinstance(base, VecSetVAE) or base.time_conditioned:
            raise ValueError("CVAE2: base must be a plain (not time-conditioned) VecSetVAE")
        width = base.bottleneck.post.out_features
        heads = heads or base.encoder.cross.attn.heads
        self.num_latents = base.num_latents
        self.latent_dim = base.latent_dim
        self.post = copy.deepcopy(base.bottleneck.post)
        self.decoder = copy.deepcopy(base.decoder)
        self.frozen = nn.ModuleDict({"embedder": base.embedder, "encoder": base.encoder, "bottleneck": base.bottleneck})
        self.frozen.requires_grad_(False)
        self.frozen.eval()
        self.time_embed = TimeEmbedding(width, num_tokens=time_tokens, freq_dim=time_freq_dim, scale=time_scale)
        self.modulator = LatentModulator(latent_dim=base.latent_dim, width=width, heads=heads, depth=modulator_depth,
                                         logvar_init=logvar_init)

    def train(self, mode: bool = True) -> "CVAE2":
        super().train(mode)
        self.frozen.eval()
        return self

    def geometry_posterior(self, surface: torch.Tensor) -> DiagonalGaussian:
        """Frozen encoder: posterior of z_geo, (B, M, latent_dim), without gradients."""
        _check_inputs(surface, None)
        with torch.no_grad():
            h = self.frozen["encoder"](surface, random_start=False)
            return self.frozen["bottleneck"].posterior(h)

    def posterior(self, surface: torch.Tensor, t: torch.Tensor | float | None = None) -> DiagonalGaussian:
        """Time-modulated posterior q(z_ctl | surface, t)."""
        prior = self.geometry_posterior(surface)
        tokens = self.time_embed(_batch_time(t, surface.shape[0], surface.device))
        return self.modulator(prior, tokens)

    def encode(self, surface: torch.Tensor, t: torch.Tensor | float | None = None, *,
               sample: bool | None = None) -> tuple[torch.Tensor, DiagonalGaussian]:
        """``(z_ctl, posterior)`` at time t; sampled in training mode unless ``sample`` says otherwise."""
        sample = self.training if sample is None else sample
        post = self.posterior(surface, t)
        return (post.sample() if sample else post.mean), post

    def latent_tokens(self, z: torch.Tensor) -> torch.Tensor:
        """(B, M, latent_dim) -> (B, M, width) decoder tokens."""
        return self.decoder.tokens(self.post(z))


def build_model(config: ModelConfig, *, load_pretrained: bool = True) -> _LatentSetModel:
    """The model a :class:`~vnc_warp.training.config.ModelConfig` describes (kind ``vae``, ``cvae1`` or ``cvae2``).

    Args:
        config: the model section of a training config.
        load_pretrained: load ``config.pretrained``, a plain VAE checkpoint: C-VAE-II's frozen encoder (and the
            decoder it starts from), or the backbone a C-VAE-I starts from (its time branch starts as the
            identity); ``False`` builds the model randomly initialised, for loading a full checkpoint afterwards.

    Raises:
        ValueError: unknown kind, C-VAE-II without ``pretrained``, or a pre-trained checkpoint whose
            architecture differs from ``config``.
        CheckpointError: ``config.pretrained`` is not a plain VAE's checkpoint.
        FileNotFoundError: ``config.pretrained`` does not exist.
    """
    backbone = config.backbone_kwargs()
    if config.kind == "vae":
        return VecSetVAE(**backbone)
    if config.kind == "cvae1":
        model = CVAE1(time_tokens=config.time_tokens, time_freq_dim=config.time_freq_dim,
                      time_scale=config.time_scale, **backbone)
        if load_pretrained and config.pretrained:
            missing, unexpected = model.load_state_dict(_pretrained_vae(config), strict=False)
            # the time branch is all a C-VAE-I adds to the VAE: anything else missing is a different architecture
            foreign = [k for k in missing if not k.startswith(("time_embed.", "encoder.condition."))]
            if foreign or unexpected:
                raise CheckpointError(f"{config.pretrained}: weights do not fit a C-VAE-I backbone (missing "
                                      f"{foreign[:3]}, unexpected {list(unexpected)[:3]})")
            # it starts as the VAE it is built on, decoding that VAE's surface at every t until the time branch learns
            model.encoder.identity_condition()
        return model
    if config.kind != "cvae2":
        raise ValueError(f"unknown model kind {config.kind!r}; expected 'vae', 'cvae1' or 'cvae2'")
    base = VecSetVAE(**backbone)
    if load_pretrained:
        if not config.pretrained:
            raise ValueError("C-VAE-II needs model.pretrained: the checkpoint of a plain VecSet VAE "
                             "(train one with the 'vae' or 'tiny-vae' config)")
        base.load_state_dict(_pretrained_vae(config))
    return CVAE2(base=base, time_tokens=config.time_tokens, time_freq_dim=config.time_freq_dim,
                 time_scale=config.time_scale, modulator_depth=config.modulator_depth, logvar_init=config.logvar_init)


def _pretrained_vae(config: ModelConfig) -> dict[str, torch.Tensor]:
    """The weights of the plain VAE checkpoint ``config.pretrained``, checked against ``config``'s backbone."""
    ckpt = load_checkpoint(config.pretrained)
    pre = ckpt["config"]["model"]
    if pre.get("kind") != "vae":
        raise CheckpointError(f"{config.pretrained}: {config.kind} needs a plain VAE checkpoint, this one is "
                              f"model.kind={pre.get('kind')!r}")
    # chunk_size sets how queries are batched, logvar_init and sdf_init only the initial weights: no architecture
    diff = {k: (pre.get(k), v) for k, v in config.backbone_kwargs().items()
            if k not in ("chunk_size", "logvar_init", "sdf_init") and pre.get(k) != v}
    if diff:
        detail = ", ".join(f"{k}: checkpoint {a!r} vs config {b!r}" for k, (a, b) in diff.items())
        raise ValueError(f"{config.pretrained}: pre-trained VAE architecture differs from model config ({detail})")
    return ckpt["model"]


def load_model(path: str | os.PathLike, *, device: str | torch.device = "cpu") -> tuple[nn.Module, TrainConfig]:
    """The model of a checkpoint, in eval mode on ``device``, and its configuration.

    Raises:
        FileNotFoundError, CheckpointError: see :func:`load_checkpoint`; CheckpointError also when the
            weights do not fit the stored configuration.
    """
    state = load_checkpoint(path)
    try:
        config = TrainConfig.from_dict(state["config"])
    except ValueError as exc:
        raise CheckpointError(f"{path}: stored config is invalid ({exc})") from exc
    model = build_model(config.model, load_pretrained=False)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match the stored model config ({exc})") from exc
    return model.to(device).eval(), config
