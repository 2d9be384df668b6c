"""Configurations of the C-VAE (Sec. 3.3): model, loss, optimiser, data and run settings.

A :class:`TrainConfig` is plain data: it round-trips through :meth:`TrainConfig.to_dict` /
:meth:`TrainConfig.from_dict` (JSON, checkpoints) and is checked by :meth:`TrainConfig.validate`.
Named configurations (:data:`NAMED_CONFIGS`, :func:`named_config`):

- ``tiny``, ``tiny-vae``, ``tiny-cvae2``: a few hundred thousand parameters, for CPU tests and smoke runs.
- ``cvae1``: C-VAE-I at the paper's latent size, 2048 x 32 (Sec. 4.3), trained from scratch.
- ``vae``: the plain VecSet VAE, 2048 x 64, the pre-trained encoder C-VAE-II needs.
- ``cvae2``: C-VAE-II, 2048 x 64 latents (Sec. 4.3), on top of a ``vae`` checkpoint.

The paper leaves widths, depths and optimiser settings to its supplement; the values here follow
Hunyuan3D-2.1's shape VAE (width 1024, 16 heads, 8 encoder and 16 decoder layers) for the 64-channel
models and a smaller 768-wide backbone for C-VAE-I.
"""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "ModelConfig",
    "LossConfig",
    "OptimConfig",
    "DataConfig",
    "TrainConfig",
    "MODEL_KINDS",
    "NAMED_CONFIGS",
    "named_config",
    "load_config",
]

MODEL_KINDS = ("vae", "cvae1", "cvae2")


@dataclass
class ModelConfig:
    """Architecture of a VecSet model (see :mod:`vnc_warp.training.model`).

    Attributes:
        kind: ``"vae"`` (plain VecSet VAE), ``"cvae1"`` (C-VAE-I) or ``"cvae2"`` (C-VAE-II).
        width: token width of every attention layer.
        heads: attention heads; ``width`` must be a multiple.
        num_latents: latent tokens M, picked from the surface by farthest-point sampling.
        latent_dim: channels C of a latent token; the latent set is (M, C).
        encoder_depth: self-attention layers of the encoder after its point cross-attention.
        decoder_depth: self-attention layers of the latent transformer.
        num_freqs: octaves of the Fourier point embedding.
        include_pi: multiply the Fourier frequencies by pi.
        mlp_ratio: hidden width of the feed-forward layers, as a multiple of ``width``.
        qkv_bias: bias in the query/key/value projections.
        qk_norm: LayerNorm on queries and keys per head.
        chunk_size: queries decoded per chunk by the query decoder.
        time_tokens: tokens the time embedding produces (C-VAE-I and C-VAE-II).
        time_freq_dim: width of the sinusoidal time features.
        time_scale: radians per unit of t of the fastest time feature: small enough that neighbouring stages get
            nearly the same features, so that a t between the stages trained on is an interpolation.
        modulator_depth: cross-attention blocks of the C-VAE-II latent modulator.
        logvar_init: initial log-variance of the posterior (the bias of the bottleneck's log-variance half, and of
            C-VAE-II's z_ctl): training decodes posterior samples, inference the mean, and both must see the
            same codes from the start (see :class:`~vnc_warp.training.model.KLBottleneck`).
        sdf_init: the SDF an untrained decoder predicts everywhere (the bias of its zero-weight head); the TSDF
            truncation starts from empty space, 0 from a surface everywhere.
        pretrained: path of a plain VAE checkpoint: C-VAE-II freezes its encoder (required); a C-VAE-I starts
            from its weights, the time branch from the identity (optional; None: from scratch).
    """

    kind: str = "cvae1"
    width: int = 64
    heads: int = 4
    num_latents: int = 32
    latent_dim: int = 8
    encoder_depth: int = 1
    decoder_depth: int = 2
    num_freqs: int = 6
    include_pi: bool = False
    mlp_ratio: float = 4.0
    qkv_bias: bool = False
    qk_norm: bool = True
    chunk_size: int = 32768
    time_tokens: int = 4
    time_freq_dim: int = 256
    time_scale: float = 10.0
    modulator_depth: int = 2
    logvar_init: float = -8.0
    sdf_init: float = 0.0
    pretrained: str | None = None

    def backbone_kwargs(self) -> dict[str, Any]:
        """Constructor arguments of :class:`~vnc_warp.training.model.VecSetVAE` (no time branch)."""
        names = ("width", "heads", "num_latents", "latent_dim", "encoder_depth", "decoder_depth", "num_freqs",
                 "include_pi", "mlp_ratio", "qkv_bias", "qk_norm", "chunk_size", "logvar_init", "sdf_init")
        return {n: getattr(self, n) for n in names}


@dataclass
class LossConfig:
    """Weights of L = L_tsdf + beta_kl L_kl + lambda_eik L_eik (Sec. 3.3) + L_surf + L_normal.

    The beta_kl curriculum (:func:`~vnc_warp.training.losses.kl_weights`): over steps, ``kl_schedule="linear"``
    raises beta linearly from ``kl_weight_start`` at step ``kl_warmup_start`` to ``kl_weight`` at
    ``kl_warmup_start + kl_warmup_steps``; over the normalized time, the KL's prior contracts from N(0, I) at
    t = 1 to N(0, I / kl_time_ratio) at t = 0 (:func:`~vnc_warp.training.losses.kl_prior_logvar`; C-VAE-I: codes
    of t -> 0 pulled toward the origin).

    Attributes:
        tsdf: ``"l1"`` or ``"mse"`` on the truncated SDF.
        near_weight: weight of the near-surface queries in L_tsdf (a weighted mean; 1: plain mean).
        kl_weight: beta_kl (final value when scheduled).
        kl_schedule: ``"constant"`` or ``"linear"``.
        kl_weight_start: beta_kl before and at the start of the warm-up.
        kl_warmup_start: first step of the warm-up.
        kl_warmup_steps: length of the warm-up in steps.
        kl_time_ratio: precision of the KL's prior at t = 0 over that at t = 1 (>= 1; 1: t-independent).
        eikonal_weight: lambda_eik; 0 skips it.
        eikonal_queries: queries per item, near-surface ones first, decoded a second time with input
            gradients for L_eik (its double backward needs the unfused attention kernel, so it is kept small).
        surface_weight: weight of L_surf = mean |f| at points on the item's surface (``data.num_on_surface``).
        normal_weight: weight of L_normal = mean (1 - cos(grad f, n)) at the same points.
    """

    tsdf: str = "l1"
    near_weight: float = 1.0
    kl_weight: float = 1e-3
    kl_schedule: str = "constant"
    kl_weight_start: float = 0.0
    kl_warmup_start: int = 0
    kl_warmup_steps: int = 0
    kl_time_ratio: float = 1.0
    eikonal_weight: float = 0.01
    eikonal_queries: int = 2048
    surface_weight: float = 0.0
    normal_weight: float = 0.0


@dataclass
class OptimConfig:
    """AdamW with linear warm-up and cosine decay to ``min_lr_ratio * lr`` at ``total_steps``.

    Attributes:
        lr: peak learning rate.
        weight_decay: AdamW decay on matrices (biases and norms are not decayed).
        betas: AdamW betas.
        eps: AdamW epsilon.
        warmup_steps: linear warm-up length.
        total_steps: length of the schedule and default length of a run.
        min_lr_ratio: final learning rate as a fraction of ``lr``.
        grad_clip: max global gradient norm; 0 disables clipping.
    """

    lr: float = 1e-4
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-8
    warmup_steps: int = 1000
    total_steps: int = 100_000
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0


@dataclass
class DataConfig:
    """Sampling and batching of trajectory items.

    Attributes:
        num_surface: surface points (xyz + normal) per item, the encoder input.
        num_queries: SDF queries per item.
        near_fraction: share of the queries drawn near the surface (the rest are uniform in the box).
        num_on_surface: points (xyz + normal) on the item's own surface per item, for L_surf and L_normal
            (0: none).
        fresh_fraction: share of the far queries drawn afresh for every item and labelled from the stage's TSDF
            grid (a dataset built with a grid; see :class:`~vnc_warp.training.data.TrajectoryDataset`).
        batch_size: items per step per process.
        num_workers: DataLoader worker processes.
        encoder_input: ``"stage0"``: the encoder sees the surface of the trajectory's stage 0 (t = 1,
            the detailed input) and the decoder the shape at the item's t, as at inference (C-VAEs);
            ``"suffix"``: the encoder sees an earlier stage s of the same trajectory (stage 0 with probability
            ``stage0_share``, else uniform over stages 1..j) and the item's t becomes ``t_j / t_s``, the time of
            stage j on the trajectory that starts at stage s (Eq. 7 divides by the S of the start; a balanced
            trajectory's suffix is a balanced trajectory); ``"item"``: the item's own surface (auto-encoding
            every stage, the plain VAE).
        stage0_share: with ``encoder_input="suffix"``, the share of items whose encoder input is stage 0.
        detail_share: with ``encoder_input="suffix"``, the share of items replaced by their shape's stage 0 at
            t = 1 (the detailed input auto-encoded; see :class:`~vnc_warp.training.train.SuffixInput`).
        symmetry: apply one of the 8 symmetries of the box's horizontal square (rotations by quarter turns about
            y, with or without the mirror x -> -x), drawn per item, to the encoder surface, the queries and the
            on-surface points alike (positions and normals); the box [-1, 1]^3 and the TSDF values are invariant.
    """

    num_surface: int = 8192
    num_queries: int = 8192
    near_fraction: float = 0.5
    num_on_surface: int = 0
    fresh_fraction: float = 0.0
    batch_size: int = 8
    num_workers: int = 4
    encoder_input: str = "stage0"
    stage0_share: float = 0.5
    detail_share: float = 0.0
    symmetry: bool = False


@dataclass
class TrainConfig:
    """Everything a training run needs besides the data path and output folder.

    Attributes:
        name: label of the configuration.
        model, loss, optim, data: the sections above.
        seed: base seed (process ``rank`` uses ``seed + rank``).
        bf16: bf16 autocast on CUDA (never on CPU).
        log_every: steps between JSONL log rows (values are averaged over the window).
        ckpt_every: steps between checkpoints (one is always written at the end).
    """

    name: str = "custom"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    data: DataConfig = field(default_factory=DataConfig)
    seed: int = 0
    bf16: bool = True
    log_every: int = 10
    ckpt_every: int = 1000

    def to_dict(self) -> dict[str, Any]:
        """Nested dict of primitives (tuples become lists), JSON- and ``weights_only``-safe."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Build and validate a config; missing keys take defaults, unknown keys are errors.

        Raises:
            ValueError: unknown key or wrong type, naming the dotted key.
        """
        cfg = _from_dict(cls, data, "")
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Check values that would fail later, deep inside a run.

        Raises:
            ValueError: with the dotted key and the offending value.
        """
        m, lo, o, d = self.model, self.loss, self.optim, self.data
        if m.kind not in MODEL_KINDS:
            raise ValueError(f"model.kind must be one of {MODEL_KINDS}, got {m.kind!r}")
        for key, value in [("model.width", m.width), ("model.heads", m.heads), ("model.num_latents", m.num_latents),
                           ("model.latent_dim", m.latent_dim), ("model.num_freqs", m.num_freqs),
                           ("model.chunk_size", m.chunk_size), ("model.time_freq_dim", m.time_freq_dim),
                           ("optim.total_steps", o.total_steps), ("data.num_surface", d.num_surface),
                           ("data.num_queries", d.num_queries), ("data.batch_size", d.batch_size),
                           ("loss.eikonal_queries", lo.eikonal_queries),
                           ("log_every", self.log_every), ("ckpt_every", self.ckpt_every)]:
            if value < 1:
                raise ValueError(f"{key} must be >= 1, got {value}")
        for key, value in [("model.encoder_depth", m.encoder_depth), ("model.decoder_depth", m.decoder_depth),
                           ("loss.kl_weight", lo.kl_weight), ("loss.kl_weight_start", lo.kl_weight_start),
                           ("loss.kl_warmup_start", lo.kl_warmup_start), ("loss.kl_warmup_steps", lo.kl_warmup_steps),
                           ("loss.eikonal_weight", lo.eikonal_weight), ("loss.surface_weight", lo.surface_weight),
                           ("loss.normal_weight", lo.normal_weight), ("loss.near_weight", lo.near_weight),
                           ("data.num_on_surface", d.num_on_surface), ("optim.weight_decay", o.weight_decay),
                           ("optim.warmup_steps", o.warmup_steps), ("optim.grad_clip", o.grad_clip),
                           ("data.num_workers", d.num_workers)]:
            if value < 0:
                raise ValueError(f"{key} must be >= 0, got {value}")
        if m.width % m.heads:
            raise ValueError(f"model.width ({m.width}) must be a multiple of model.heads ({m.heads})")
        if (m.width // m.heads) % 2:
            raise ValueError(f"model.width / model.heads must be even, got {m.width // m.heads}")
        if not m.time_scale > 0:
            raise ValueError(f"model.time_scale must be > 0, got {m.time_scale}")
        if m.time_freq_dim % 2:
            raise ValueError(f"model.time_freq_dim must be even, got {m.time_freq_dim}")
        if m.kind in ("cvae1", "cvae2") and m.time_tokens < 1:
            raise ValueError(f"model.time_tokens must be >= 1 for {m.kind}, got {m.time_tokens}")
        if m.kind == "cvae2" and m.modulator_depth < 1:
            raise ValueError(f"model.modulator_depth must be >= 1 for cvae2, got {m.modulator_depth}")
        if m.num_latents > d.num_surface:
            raise ValueError(f"model.num_latents ({m.num_latents}) exceeds data.num_surface ({d.num_surface}): "
                             "farthest-point sampling picks the latent queries among the surface points")
        if d.encoder_input not in ("stage0", "suffix", "item"):
            raise ValueError(f"data.encoder_input must be 'stage0', 'suffix' or 'item', got {d.encoder_input!r}")
        if not 0.0 <= d.stage0_share <= 1.0:
            raise ValueError(f"data.stage0_share must be in [0, 1], got {d.stage0_share}")
        if not 0.0 <= d.detail_share <= 1.0:
            raise ValueError(f"data.detail_share must be in [0, 1], got {d.detail_share}")
        if lo.tsdf not in ("l1", "mse"):
            raise ValueError(f"loss.tsdf must be 'l1' or 'mse', got {lo.tsdf!r}")
        if not lo.kl_time_ratio >= 1.0:
            raise ValueError(f"loss.kl_time_ratio must be >= 1 (prior precision at t = 0 over t = 1), "
                             f"got {lo.kl_time_ratio}")
        if not 0.0 <= d.near_fraction <= 1.0:
            raise ValueError(f"data.near_fraction must be in [0, 1], got {d.near_fraction}")
        if not 0.0 <= d.fresh_fraction <= 1.0:
            raise ValueError(f"data.fresh_fraction must be in [0, 1], got {d.fresh_fraction}")
        if (lo.surface_weight > 0 or lo.normal_weight > 0) and d.num_on_surface < 1:
            raise ValueError("loss.surface_weight / loss.normal_weight need data.num_on_surface >= 1 points on "
                             "each item's surface")
        if lo.kl_schedule not in ("constant", "linear"):
            raise ValueError(f"loss.kl_schedule must be 'constant' or 'linear', got {lo.kl_schedule!r}")
        if not o.lr > 0:
            raise ValueError(f"optim.lr must be > 0, got {o.lr}")
        if not 0.0 <= o.min_lr_ratio <= 1.0:
            raise ValueError(f"optim.min_lr_ratio must be in [0, 1], got {o.min_lr_ratio}")


def _from_dict(cls: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        section = prefix.rstrip(".") or "<root>"
        raise ValueError(f"config section {section} must be a JSON object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ValueError(f"unknown config key(s) {', '.join(prefix + u for u in unknown)}; "
                         f"valid keys here: {', '.join(prefix + n for n in names)}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        key = prefix + name
        if dataclasses.is_dataclass(hint):
            kwargs[name] = _from_dict(hint, value, key + ".")
        else:
            kwargs[name] = _coerce(value, hint, key)
    return cls(**kwargs)


def _coerce(value: Any, hint: Any, key: str) -> Any:
    """Check ``value`` against a simple annotation (int, float, bool, str, Optional, tuple)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ValueError(f"config key {key} must be a list of {len(args)} numbers, got {value!r}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif hint is str:
        ok = isinstance(value, str)
    else:
        ok = True
    if not ok:
        raise ValueError(f"config key {key} must be {getattr(hint, '__name__', hint)}, got {value!r}")
    return value


def _tiny(kind: str) -> TrainConfig:
    return TrainConfig(
        name="tiny" if kind == "cvae1" else f"tiny-{kind}",
        model=ModelConfig(kind=kind, width=64, heads=4, num_latents=32, latent_dim=8, encoder_depth=1,
                          decoder_depth=2, num_freqs=6, chunk_size=4096, time_tokens=2, time_freq_dim=64,
                          modulator_depth=1),
        loss=LossConfig(kl_weight=1e-4, kl_schedule="linear" if kind == "cvae1" else "constant",
                        kl_weight_start=0.0, kl_warmup_steps=50 if kind == "cvae1" else 0, eikonal_weight=0.01,
                        eikonal_queries=64),
        optim=OptimConfig(lr=1e-3, weight_decay=0.0, warmup_steps=10, total_steps=200, min_lr_ratio=0.1),
        data=DataConfig(num_surface=256, num_queries=256, batch_size=4, num_workers=0,
                        encoder_input="item" if kind == "vae" else "stage0"),
        seed=0, log_every=1, ckpt_every=50,
    )


def _paper(kind: str) -> TrainConfig:
    wide = kind in ("vae", "cvae2")
    model = ModelConfig(
        kind=kind, width=1024 if wide else 768, heads=16 if wide else 12, num_latents=2048,
        latent_dim=64 if wide else 32, encoder_depth=8 if wide else 4, decoder_depth=16 if wide else 12,
        num_freqs=8, include_pi=False, qkv_bias=False, qk_norm=True, chunk_size=32768,
        time_tokens=4, time_freq_dim=256, modulator_depth=4)
    if kind == "cvae1":
        loss = LossConfig(kl_weight=1e-3, kl_schedule="linear", kl_weight_start=0.0, kl_warmup_start=5_000,
                          kl_warmup_steps=50_000, eikonal_weight=0.01)
        optim = OptimConfig(lr=1e-4, warmup_steps=2_000, total_steps=300_000)
    elif kind == "vae":
        loss = LossConfig(kl_weight=1e-3, eikonal_weight=0.01)
        optim = OptimConfig(lr=1e-4, warmup_steps=2_000, total_steps=300_000)
    else:
        loss = LossConfig(kl_weight=1e-4, eikonal_weight=0.01)
        optim = OptimConfig(lr=5e-5, warmup_steps=500, total_steps=50_000)
    return TrainConfig(name=kind, model=model, loss=loss, optim=optim,
                       data=DataConfig(num_surface=16384, num_queries=16384, batch_size=8, num_workers=6,
                                       encoder_input="item" if kind == "vae" else "stage0"),
                       bf16=True, log_every=20, ckpt_every=2_000)


NAMED_CONFIGS: dict[str, Any] = {
    "tiny": lambda: _tiny("cvae1"),
    "tiny-vae": lambda: _tiny("vae"),
    "tiny-cvae2": lambda: _tiny("cvae2"),
    "cvae1": lambda: _paper("cvae1"),
    "vae": lambda: _paper("vae"),
    "cvae2": lambda: _paper("cvae2"),
}


def named_config(name: str) -> TrainConfig:
    """A fresh copy of a named configuration (see the module docstring).

    Raises:
        ValueError: unknown name, listing the known ones.
    """
    if name not in NAMED_CONFIGS:
        raise ValueError(f"unknown config name {name!r}; named configs: {', '.join(NAMED_CONFIGS)}")
    return NAMED_CONFIGS[name]()


def load_config(name_or_path: str | os.PathLike) -> TrainConfig:
    """A named configuration, or a JSON file holding :meth:`TrainConfig.to_dict` (possibly partial).

    Raises:
        FileNotFoundError: neither a named config nor an existing file.
        ValueError: unreadable JSON or invalid content.
    """
    text = os.fspath(name_or_path)
    if text in NAMED_CONFIGS:
        return named_config(text)
    path = Path(text)
    if not path.is_file():
        raise FileNotFoundError(f"config {text!r} is neither a named config ({', '.join(NAMED_CONFIGS)}) "
                                "nor an existing JSON file")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read config JSON ({exc})") from exc
    try:
        return TrainConfig.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
