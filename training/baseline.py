"""The latent-interpolation baseline of Sec. 4.3 / Tab. 2, which the C-VAE is compared against.

A plain VecSet VAE (:class:`~vnc_warp.training.model.VecSetVAE`, no time condition, the same size as
the C-VAE) encodes the two ends of a VNC-Flow trajectory: stage 0 (t = 1, the detailed input) and
the last stage (the base shape, t -> 0). The prediction at time t decodes the linear blend

    z(t) = alpha z_start + (1 - alpha) z_end,   alpha = clip((t - t_end) / (1 - t_end), 0, 1),

with ``t_end`` the normalized time the last stage reached (Eq. (7)): the blend passes through both
encoded endpoints exactly at their own times, and earlier ``t`` keep the last stage's latent. The
baseline sees the ground-truth base shape, which the C-VAE does not; it still has to guess every
intermediate shape from a straight line in latent space, which is what the comparison measures.

Both endpoints are normalized with the trajectory's stage-0 normalization, as the training data is
(:func:`vnc_warp.training.data.normalization`), so one latent space and one frame hold the whole path.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from vnc_warp.mesh import Mesh

from .data import normalization, read_trajectory
from .inference import _check_times, extract_mesh, sdf_grid_tensor, surface_condition, write_predictions

__all__ = ["interpolation_alpha", "interpolate_latents", "encode_surface", "LatentInterpolation",
           "latent_interpolation"]


def interpolation_alpha(t: float, *, t_start: float = 1.0, t_end: float = 0.0) -> float:
    """Weight of the start latent at time ``t``: ``clip((t - t_end) / (t_start - t_end), 0, 1)``.

    Raises:
        ValueError: ``t_start <= t_end``.
    """
    if not t_start > t_end:
        raise ValueError(f"interpolation_alpha: need t_start > t_end, got {t_start} and {t_end}")
    return float(np.clip((float(t) - t_end) / (t_start - t_end), 0.0, 1.0))


def interpolate_latents(z_start: torch.Tensor, z_end: torch.Tensor, alpha: float) -> torch.Tensor:
    """``alpha * z_start + (1 - alpha) * z_end`` for latent sets of one shape, e.g. (1, M, C).

    ``alpha = 1`` returns ``z_start`` and ``alpha = 0`` returns ``z_end`` bit for bit.

    Raises:
        ValueError: shapes differ or alpha outside [0, 1].
    """
    if z_start.shape != z_end.shape:
        raise ValueError(f"interpolate_latents: latent shapes differ, {tuple(z_start.shape)} and {tuple(z_end.shape)}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"interpolate_latents: alpha must be in [0, 1], got {alpha}")
    if alpha == 1.0:
        return z_start.clone()
    if alpha == 0.0:
        return z_end.clone()
    return torch.lerp(z_end, z_start, float(alpha))


@torch.no_grad()
def encode_surface(model: torch.nn.Module, surface: np.ndarray | torch.Tensor,
                   t: float | None = None) -> torch.Tensor:
    """Posterior-mean latents (1, M, C) of an (N, 6) normalized surface sample (deterministic FPS start).

    Args:
        model: a VecSet model in eval mode.
        surface: (N, 6) float32 normalized xyz + unit normal
            (see :func:`~vnc_warp.training.inference.surface_condition`).
        t: normalised time, required by a time-conditioned model and ignored by a plain VAE.
    """
    device = next(model.parameters()).device
    x = torch.as_tensor(surface, dtype=torch.float32, device=device)
    if x.ndim != 2 or x.shape[1] != 6:
        raise ValueError(f"encode_surface: surface must be (N, 6), got {tuple(x.shape)}")
    tt = None if t is None else torch.tensor([float(t)], device=device)
    z, _ = model.encode(x.unsqueeze(0), tt, sample=False)
    return z.float()


class LatentInterpolation:
    """The baseline for one trajectory: endpoint latents of a plain VAE and their linear blend.

    Args:
        model: a plain (not time-conditioned) VecSet VAE in eval mode.
        start: the stage-0 mesh (t = 1), any units.
        end: the last-stage mesh (base shape), same units.
        t_end: the normalized time of ``end`` (Eq. (7)); 0 treats it as the exact t = 0 endpoint.
        num_surface: encoder surface samples per endpoint.
        seed: surface sampling seed.

    Attributes:
        z_start, z_end: (1, M, C) posterior means of the endpoints.
        center, scale: the stage-0 normalization shared by both endpoints and every decoded mesh.
    """

    def __init__(self, model: torch.nn.Module, start: Mesh, end: Mesh, *, t_end: float = 0.0, num_surface: int = 8192,
                 seed: int = 0) -> None:
        if getattr(model, "time_conditioned", True):
            raise ValueError("LatentInterpolation: the baseline needs a plain VecSet VAE (model.kind 'vae'), "
                             "not a time-conditioned C-VAE")
        if not 0.0 <= t_end < 1.0:
            raise ValueError(f"LatentInterpolation: t_end must be in [0, 1), got {t_end}")
        self.model, self.t_end = model, float(t_end)
        self.center, self.scale = normalization(start)
        norm = (self.center, self.scale)
        self.z_start = encode_surface(model, surface_condition(start, num_points=num_surface, seed=seed,
                                                               normalization=norm)[0])
        self.z_end = encode_surface(model, surface_condition(end, num_points=num_surface, seed=seed,
                                                             normalization=norm)[0])

    def latent(self, t: float) -> torch.Tensor:
        """(1, M, C) latents at normalized time ``t``."""
        return interpolate_latents(self.z_start, self.z_end, interpolation_alpha(t, t_end=self.t_end))

    def decode(self, t: float, *, resolution: int = 128, name: str = "interpolated") -> Mesh:
        """The mesh at time ``t`` in the units of the input (marching cubes on a ``resolution``^3 grid).

        Raises:
            ValueError: the decoded SDF has no zero crossing on the grid.
        """
        sdf = sdf_grid_tensor(self.model, self.latent(t), resolution=resolution)
        return extract_mesh(sdf, center=self.center, scale=self.scale, name=name)


def latent_interpolation(model: torch.nn.Module, traj_dir: str | os.PathLike, times: Sequence[float],
                         out_dir: str | os.PathLike, *, resolution: int = 128, num_surface: int = 8192, seed: int = 0,
                         endpoint_t: str = "measured", file_format: str = "ply") -> dict[str, Any]:
    """Run the baseline on a trajectory and write its meshes like ``vnc-warp generate`` does.

    Args:
        model: a plain VecSet VAE in eval mode.
        traj_dir: a VNC-Flow trajectory directory (``manifest.json`` + stages).
        times: normalised times in [0, 1] to decode.
        out_dir: output folder: one mesh per time and ``generate.json`` (readable by
            :func:`~vnc_warp.training.metrics.read_prediction_dir`).
        resolution: marching-cubes grid samples per axis.
        num_surface: encoder surface samples per endpoint.
        seed: surface sampling seed.
        endpoint_t: ``"measured"``: the last stage sits at the t it reached; ``"zero"``: at t = 0.
        file_format: mesh file extension.

    Returns:
        The content of ``generate.json``, with ``method``, ``trajectory``, ``t_end`` and the normalization.
    """
    if endpoint_t not in ("measured", "zero"):
        raise ValueError(f"latent_interpolation: endpoint_t must be 'measured' or 'zero', got {endpoint_t!r}")
    times = _check_times(times)
    traj = read_trajectory(traj_dir)
    if len(traj.stages) < 2:
        raise ValueError(f"latent_interpolation: {traj.root} has a single stage; two endpoints are needed")
    t_end = traj.stages[-1].t if endpoint_t == "measured" else 0.0
    interp = LatentInterpolation(model, traj.load_stage(0), traj.load_stage(len(traj.stages) - 1), t_end=t_end,
                                 num_surface=num_surface, seed=seed)

    def decode(t: float, name: str) -> Mesh:
        return interp.decode(t, resolution=resolution, name=name)

    meta = {"method": "latent_interpolation", "trajectory": str(traj.root), "t_end": t_end,
            "center": [float(c) for c in interp.center], "scale": float(interp.scale), "resolution": resolution,
            "num_surface": num_surface, "seed": seed}
    return write_predictions(out_dir, times, decode, stem=Path(traj.root).name, file_format=file_format, meta=meta)
