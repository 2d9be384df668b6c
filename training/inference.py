"""Inference: encode a mesh, decode the SDF at time t on a grid in chunks, extract a :class:`~vnc_warp.Mesh`.

The input is normalised with the rule of the training data (``x_norm = (x - center) * scale``,
bounding-box centre and ``scale = 1.8 / max extent``, see :func:`vnc_warp.training.data.normalization`);
decoded meshes are mapped back to the input's units.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from vnc_warp.mesh import Mesh, MeshError, from_arrays, load_mesh

from .checkpoint import load_model
from .train import resolve_device

__all__ = ["surface_condition", "sdf_grid_tensor", "decode_sdf_grid", "extract_mesh", "decode_mesh", "write_predictions", "predict_times",
           "generate"]


def _model_device(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


def surface_condition(mesh: Mesh, *, num_points: int, seed: int = 0,
                      normalization: tuple[Sequence[float], float] | None = None
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Encoder input of a mesh: normalised surface points and unit normals.

    Args:
        mesh: the surface to encode, any units.
        num_points: surface samples (area-weighted).
        seed: sampling seed.
        normalization: ``(center (3,), scale)`` to apply, ``x_norm = (x - center) * scale``; None
            computes the mesh's own (:func:`vnc_warp.training.data.normalization`). Later stages of a
            trajectory take the normalization of its stage 0, as in the training data.

    Returns:
        ``(surface, center, scale)``: (num_points, 6) float32 normalised xyz + normal, (3,) float64, float.
    """
    from .data import normalization as own_normalization, sample_surface

    if normalization is None:
        center, scale = own_normalization(mesh)
    else:
        center, scale = np.asarray(normalization[0], dtype=np.float64), float(normalization[1])
    points, normals = sample_surface(mesh, num_points, np.random.default_rng(seed))
    surface = np.concatenate([(points - center) * scale, normals], axis=1).astype(np.float32)
    return surface, center, scale


@torch.no_grad()
def sdf_grid_tensor(model: torch.nn.Module, latents: torch.Tensor, *, resolution: int = 128, bound: float = 1.0,
                    chunk_size: int | None = None, amp: bool | None = None) -> torch.Tensor:
    """:func:`decode_sdf_grid` as a float32 tensor on the model's device (no host copy)."""
    if resolution < 2:
        raise ValueError(f"decode_sdf_grid: resolution must be >= 2, got {resolution}")
    device = _model_device(model)
    z = latents.to(device).float()
    if z.ndim == 2:
        z = z.unsqueeze(0)
    if z.ndim != 3 or z.shape[0] != 1:
        raise ValueError(f"decode_sdf_grid: latents must be (M, C) or (1, M, C), got {tuple(latents.shape)}")
    if amp is None:
        amp = device.type == "cuda" and torch.cuda.is_bf16_supported()
    axis = torch.linspace(-bound, bound, resolution, device=device)
    sdf = torch.empty(resolution**3, device=device)
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
        tokens = model.latent_tokens(z)
        # the grid is made slab by slab along x, so a 256^3 decode never holds all 16.7M query points
        slab = resolution * resolution
        for i in range(resolution):
            yz = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)
            q = torch.cat([axis[i].expand(slab, 1), yz], dim=1).unsqueeze(0)
            sdf[i * slab:(i + 1) * slab] = model.decoder.queries(tokens, q, chunk_size=chunk_size)[0].float()
    return sdf.reshape(resolution, resolution, resolution)


def decode_sdf_grid(model: torch.nn.Module, latents: torch.Tensor, *, resolution: int = 128, bound: float = 1.0,
                    chunk_size: int | None = None, amp: bool | None = None) -> np.ndarray:
    """SDF of one latent set on the regular grid ``linspace(-bound, bound, resolution)^3``.

    The latent transformer runs once; the query decoder runs over the grid in chunks, every grid point decoded
    (no coarse-to-fine shortcut that could miss a fragment).

    Args:
        model: a VecSet model (:mod:`vnc_warp.training.model`).
        latents: (M, C) or (1, M, C) latents.
        resolution: samples per axis.
        bound: half-width of the grid, normalised units.
        chunk_size: queries per decoder call (default: the model's).
        amp: bf16 autocast (the SDF head stays float32, as in training); None: on CUDA when supported.

    Returns:
        (resolution, resolution, resolution) float32 SDF, indexed [x, y, z].
    """
    return sdf_grid_tensor(model, latents, resolution=resolution, bound=bound, chunk_size=chunk_size,
                           amp=amp).cpu().numpy()


def _marching_cubes(sdf: np.ndarray | torch.Tensor, level: float, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64, on ``[-bound, bound]^3``) and faces wound outward for a field negative inside.

    A torch tensor runs through Warp's marching cubes on its device (in place on a GPU); a NumPy array
    through scikit-image's.
    """
    if isinstance(sdf, torch.Tensor):
        import warp as wp
        import warp.geometry

        from vnc_warp._device import get_device

        get_device(sdf.device)  # Warp initialised (quietly) before it reads the tensor
        field = wp.from_torch((sdf.float() - level).contiguous(), dtype=wp.float32)
        stream = wp.stream_from_torch(sdf.device) if sdf.is_cuda else None
        with wp.ScopedStream(stream):
            verts, idx = warp.geometry.IsoSurfaceMarchingCubes.extract(field, 0.0, lower=(-bound,) * 3,
                                                                        upper=(bound,) * 3)
        # Warp winds faces outward for a field that grows outward (checked against a sphere's volume)
        return verts.numpy().astype(np.float64), idx.numpy().reshape(-1, 3).astype(np.int64)
    from skimage.measure import marching_cubes

    step = 2.0 * bound / (sdf.shape[0] - 1)
    # 'ascent' winds faces so that normals point toward increasing values: outward for an SDF.
    verts, faces, _, _ = marching_cubes(sdf, level=level, spacing=(step, step, step), gradient_direction="ascent")
    return verts - bound, faces


def extract_mesh(sdf: np.ndarray | torch.Tensor, *, bound: float = 1.0, level: float = 0.0,
                 center: Sequence[float] | None = None, scale: float | None = None, name: str = "decoded") -> Mesh:
    """Marching cubes on a grid SDF, negative inside, with outward winding.

    Args:
        sdf: (R, R, R) samples on ``linspace(-bound, bound, R)^3``, indexed [x, y, z]: NumPy (scikit-image's
            marching cubes) or a torch tensor (Warp's, on the tensor's device).
        bound: half-width of the grid.
        level: iso-value.
        center, scale: undo the normalisation, ``x = x_norm / scale + center`` (both or neither).
        name: mesh name.

    Raises:
        ValueError: the grid has no crossing of ``level``.
    """
    import trimesh

    if not isinstance(sdf, torch.Tensor):
        sdf = np.asarray(sdf, dtype=np.float32)
    lo, hi = float(sdf.min()), float(sdf.max())
    if not lo < level < hi:
        raise ValueError(f"{name}: the decoded SDF has no {level} crossing on the grid (min {lo:.4g}, max {hi:.4g}); "
                         "nothing to mesh")
    verts, faces = _marching_cubes(sdf, level, bound)
    if (center is None) != (scale is None):
        raise ValueError("extract_mesh: give both center and scale, or neither")
    if scale is not None:
        verts = verts / scale + np.asarray(center, dtype=np.float64)
    # Mesh stores float32: round first, so that vertices float32 cannot tell apart are merged here and
    # the faces they would degenerate are dropped, instead of reappearing when the mesh is saved and read.
    tm = trimesh.Trimesh(verts.astype(np.float32).astype(np.float64), faces, process=True)
    # Grid samples exactly at the level make slivers of (near) zero area, which Mesh rejects; they carry
    # no surface, so they go, with a margin above Mesh's own 1e-12 relative threshold.
    area2 = 2.0 * tm.area_faces
    keep = tm.nondegenerate_faces() & (area2 > 1e-10 * float(np.sum(tm.extents**2)))
    tm.update_faces(keep)
    tm.remove_unreferenced_vertices()
    try:
        return from_arrays(tm.vertices, tm.faces, name=name)
    except MeshError as exc:
        raise MeshError(f"marching cubes output is not a usable mesh: {exc}") from exc


@torch.no_grad()
def decode_mesh(model: torch.nn.Module, latents_or_cond: torch.Tensor | np.ndarray, t: float | None = None, *,
                resolution: int = 128, bound: float = 1.0, chunk_size: int | None = None,
                center: Sequence[float] | None = None, scale: float | None = None, name: str = "decoded") -> Mesh:
    """Decode a mesh from latents, or from a surface condition at time ``t``.

    Args:
        model: a VecSet model in eval mode.
        latents_or_cond: with ``t=None``, latents (M, C) or (1, M, C) from ``model.encode``; with ``t``,
            the encoder input (N, 6) or (1, N, 6): normalised xyz + unit normal of the detailed shape
            (see :func:`surface_condition`), encoded at ``t`` with the posterior mean.
        t: normalised evolution time in [0, 1] (Eq. (7)); ignored by a plain VAE.
        resolution, bound, chunk_size: see :func:`decode_sdf_grid`.
        center, scale: undo the normalisation (see :func:`extract_mesh`).
        name: mesh name.

    Returns:
        The zero level set as a :class:`~vnc_warp.Mesh`.
    """
    device = _model_device(model)
    x = torch.as_tensor(latents_or_cond, dtype=torch.float32, device=device)
    if t is None:
        latents = x
    else:
        if not 0.0 <= float(t) <= 1.0:
            raise ValueError(f"decode_mesh: t must be in [0, 1], got {t}")
        surface = x.unsqueeze(0) if x.ndim == 2 else x
        if surface.ndim != 3 or surface.shape[0] != 1 or surface.shape[-1] != 6:
            raise ValueError(f"decode_mesh: with t, the condition must be an (N, 6) surface sample, "
                             f"got {tuple(x.shape)}")
        latents, _ = model.encode(surface, torch.tensor([float(t)], device=device), sample=False)
    sdf = sdf_grid_tensor(model, latents, resolution=resolution, bound=bound, chunk_size=chunk_size)
    return extract_mesh(sdf, bound=bound, center=center, scale=scale, name=name)


def write_predictions(out_dir: str | os.PathLike, times: Sequence[float], decode: Callable[[float, str], Mesh], *,
                      stem: str, file_format: str = "ply", meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """Decode one mesh per time with ``decode(t, name)`` and write them plus ``generate.json``.

    The listing is what :func:`vnc_warp.training.metrics.read_prediction_dir` reads, for any
    predictor (C-VAE, latent interpolation): a time whose decode raises ``ValueError`` / ``MeshError``
    (e.g. an empty level set) is listed with ``"file": null`` and the error.

    Args:
        out_dir: output folder (created).
        times: normalised times in [0, 1].
        decode: ``(t, name) -> Mesh`` in world units.
        stem: file name stem; the mesh of time t is ``<stem>_t<t:.3f>.<file_format>``.
        file_format: mesh file extension.
        meta: extra entries of ``generate.json``.

    Returns:
        The content of ``generate.json``: ``meta``, ``"frame": "world"`` and ``"meshes"``, one entry per
        time with ``t``, ``file`` (or None and ``error``), ``vertices``, ``faces``, ``watertight``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for t in times:
        name = f"{stem}_t{t:.3f}"
        entry: dict[str, Any] = {"t": float(t)}
        try:
            result = decode(float(t), name)
        except (ValueError, MeshError) as exc:
            entry.update(file=None, error=str(exc))
        else:
            path = out / f"{name}.{file_format}"
            result.save(path)
            entry.update(file=path.name, vertices=result.num_vertices, faces=result.num_faces,
                         watertight=result.is_watertight)
        entries.append(entry)
    report = {**(meta or {}), "frame": "world", "meshes": entries}
    tmp = out / "generate.json.tmp"
    tmp.write_text(json.dumps(report, indent=2) + "\n")
    os.replace(tmp, out / "generate.json")
    return report


def predict_times(model: torch.nn.Module, mesh: str | os.PathLike | Mesh, times: Sequence[float],
                  out_dir: str | os.PathLike, *, num_surface: int, resolution: int = 128, seed: int = 0,
                  file_format: str = "ply", name: str | None = None, meta: dict[str, Any] | None = None
                  ) -> dict[str, Any]:
    """Predict the shape of ``mesh`` at each time with a loaded model (see :func:`generate`).

    Args:
        model: a VecSet model in eval mode; a C-VAE encodes the detailed input at each t, a plain VAE
            reconstructs the input whatever t.
        mesh: the detailed input (t = 1), any units.
        times: normalised times in [0, 1].
        out_dir: output folder.
        num_surface: encoder surface samples.
        resolution: marching-cubes grid samples per axis.
        seed: surface sampling seed.
        file_format: mesh file extension.
        name: file name stem (default: the mesh's name).
        meta: extra entries of ``generate.json``.

    Returns:
        The content of ``generate.json`` (see :func:`write_predictions`) with the normalization.
    """
    times = _check_times(times)
    src = load_mesh(mesh)
    surface, center, scale = surface_condition(src, num_points=num_surface, seed=seed)

    def decode(t: float, mesh_name: str) -> Mesh:
        return decode_mesh(model, surface, t, resolution=resolution, center=center, scale=scale, name=mesh_name)

    meta = {**(meta or {}), "input": str(mesh) if not isinstance(mesh, Mesh) else mesh.name,
            "time_conditioned": bool(model.time_conditioned), "center": [float(c) for c in center],
            "scale": float(scale), "resolution": resolution, "num_surface": num_surface, "seed": seed}
    return write_predictions(out_dir, times, decode, stem=name or Path(src.name).stem or "mesh",
                             file_format=file_format, meta=meta)


def _check_times(times: Sequence[float]) -> list[float]:
    times = [float(t) for t in times]
    bad = [t for t in times if not 0.0 <= t <= 1.0]
    if not times or bad:
        raise ValueError(f"times must be a non-empty list of values in [0, 1], got {times}")
    return times


def generate(checkpoint: str | os.PathLike, mesh: str | os.PathLike | Mesh, times: Sequence[float],
             out_dir: str | os.PathLike, *, resolution: int = 128, device: str | torch.device | None = None,
             num_surface: int | None = None, seed: int = 0, file_format: str = "ply") -> dict[str, Any]:
    """Predict the shape of ``mesh`` at each time in ``times`` and write one mesh per time plus ``generate.json``.

    Args:
        checkpoint: a training checkpoint (or a run folder with ``checkpoints/last.pt``).
        mesh: the detailed input (path or :class:`~vnc_warp.Mesh`), any units.
        times: normalised times in [0, 1].
        out_dir: output folder (created).
        resolution: grid samples per axis for marching cubes.
        device: torch device (None: CUDA when present).
        num_surface: encoder surface samples (default: the checkpoint's ``data.num_surface``).
        seed: surface sampling seed.
        file_format: mesh file extension (``ply``, ``obj``, ...).

    Returns:
        The content of ``generate.json``: inputs, normalisation, and per time the file written (or
        the reason none was, e.g. an empty level set) with vertex and face counts.
    """
    times = _check_times(times)
    model, config = load_model(checkpoint, device=resolve_device(device))
    return predict_times(model, mesh, times, out_dir, num_surface=num_surface or config.data.num_surface,
                         resolution=resolution, seed=seed, file_format=file_format,
                         meta={"checkpoint": str(checkpoint), "model_kind": config.model.kind})
