"""Truncated-SDF training data from VNC-Flow trajectories (Sec. 3.3, trained with L_tsdf).

A trajectory directory (written by VNC-Flow, Algorithm 1) holds stage meshes and the ``manifest.json`` that
lists them with their times and checksums, stage 0 at ``t = 1`` (Eq. (7)); it is read through
:mod:`vnc_warp.trajectory` (the one trajectory format), which refuses damaged or foreign stage files, and only
the stages listed count. :func:`build_dataset` samples every
stage once into ``<out>/<shape>/stage_<index>.npz`` and writes ``<out>/index.json``; every stage of a
trajectory shares the normalization of its stage 0 (``x_norm = (x - center) * scale`` with
``center`` the bounding-box centre and ``scale = 1.8 / max extent``), so ``t`` is the only thing that
changes along a trajectory. :class:`TrajectoryDataset` reads the samples, checks each file against
its SHA-256 in the index and its arrays for finiteness, and draws random subsets per item.

Sample file keys: ``surface`` (Ns, 6) float32 xyz + unit normal, ``queries`` (Nq, 3) float32,
``tsdf`` (Nq,) float32 in [-truncation, truncation] (negative inside), ``near`` (Nq,) bool (query drawn
near the surface), ``t`` () float32, ``config`` () str (JSON of the settings that produced the file).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import warnings
import zlib
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import warp as wp

from vnc_warp._device import get_device
from vnc_warp._files import output_dir
from vnc_warp.mesh import Mesh, MeshError
from vnc_warp.sdf import signed_distance
from vnc_warp.trajectory import FORMAT as TRAJECTORY_FORMAT
from vnc_warp.trajectory import Trajectory, TrajectoryError, TrajectoryStage, read_trajectory

__all__ = [
    "DATASET_FORMAT",
    "TRAJECTORY_FORMAT",
    "DatasetError",
    "Trajectory",
    "TrajectoryError",
    "TrajectoryStage",
    "TrajectoryDataset",
    "build_dataset",
    "normalization",
    "read_trajectory",
    "sample_surface",
    "verify_dataset",
]

DATASET_FORMAT = "vnc-warp-tsdf/1"
_SAMPLE_KEYS = ("surface", "queries", "tsdf", "near", "t", "config")


class DatasetError(ValueError):
    """A dataset or trajectory that cannot be used; the message names the file and what is wrong."""


def normalization(mesh: Mesh) -> tuple[np.ndarray, float]:
    """Centre and scale that map ``mesh`` into [-0.9, 0.9]^3: ``x_norm = (x - center) * scale``.

    Returns:
        ``center`` (3,) float64 (bounding-box centre) and ``scale = 1.8 / max bbox extent``.
    """
    v = mesh.vertices.astype(np.float64)
    lo, hi = v.min(0), v.max(0)
    extent = float((hi - lo).max())
    if not extent > 0.0:
        raise MeshError(f"{mesh.name}: zero bounding-box extent, cannot normalize")
    return 0.5 * (lo + hi), 1.8 / extent


def sample_surface(mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform points on the surface and the unit normals of their faces.

    Args:
        mesh: the surface: a :class:`Mesh` or anything with ``vertices`` (V, 3) and ``faces`` (F, 3)
            (zero-area faces are never drawn).
        n: number of points.
        rng: random generator (the only source of randomness).

    Returns:
        points (n, 3) float64 and normals (n, 3) float64 (outward for a closed :class:`Mesh`).
    """
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    cdf = np.cumsum(area2)
    face = np.minimum(np.searchsorted(cdf, rng.uniform(0.0, cdf[-1], size=n), side="right"), f.shape[0] - 1)
    r1 = np.sqrt(rng.uniform(size=(n, 1)))
    r2 = rng.uniform(size=(n, 1))
    points = (1.0 - r1) * a[face] + r1 * (1.0 - r2) * b[face] + r1 * r2 * c[face]
    return points, cross[face] / area2[face, None]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _read_sample(path: Path, expected_sha: str | None = None) -> dict[str, np.ndarray]:
    """Load and check one sample file; raises :class:`DatasetError` naming the file and the fault."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read sample file ({exc})") from exc
    if expected_sha is not None and hashlib.sha256(data).hexdigest() != expected_sha:
        raise DatasetError(f"{path}: checksum mismatch with index.json (corrupt or partially written file)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except Exception as exc:  # zipfile/numpy raise many types for damaged archives
        raise DatasetError(f"{path}: cannot load sample file ({type(exc).__name__}: {exc})") from exc
    missing = [k for k in _SAMPLE_KEYS if k not in arrays]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {missing} (found {sorted(arrays)})")
    s, q, d, near = arrays["surface"], arrays["queries"], arrays["tsdf"], arrays["near"]
    nq = q.shape[0] if q.ndim == 2 else -1
    if (s.ndim != 2 or s.shape[1] != 6 or s.dtype != np.float32 or q.ndim != 2 or q.shape[1] != 3
            or q.dtype != np.float32 or d.shape != (nq,) or d.dtype != np.float32 or near.shape != (nq,)
            or near.dtype != np.bool_):
        raise DatasetError(f"{path}: bad array shapes/dtypes: surface {s.shape} {s.dtype}, queries {q.shape} "
                           f"{q.dtype}, tsdf {d.shape} {d.dtype}, near {near.shape} {near.dtype}")
    grid = arrays.get("grid")
    if grid is not None and (grid.ndim != 3 or len(set(grid.shape)) != 1 or grid.dtype != np.float32):
        raise DatasetError(f"{path}: bad TSDF grid {grid.shape} {grid.dtype}, expected (R, R, R) float32")
    _check_finite(arrays, path)
    return arrays


def _check_finite(arrays: dict[str, np.ndarray], where) -> None:
    """Refuse NaN or infinite values: one would make every loss it enters NaN, silently, until the end of a run."""
    for key in ("surface", "queries", "tsdf", "t", *(("grid",) if "grid" in arrays else ())):
        bad = int(np.size(arrays[key]) - np.count_nonzero(np.isfinite(arrays[key])))
        if bad:
            raise DatasetError(f"{where}: {bad} non-finite value(s) (NaN or infinite) in {key!r}")


def _write_sample(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write atomically (temporary file + rename) and return the file's SHA-256."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, path)
    return _sha256(path)


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1))
    os.replace(tmp, path)


def _read_index(root: Path) -> dict:
    path = root / "index.json"
    if not path.is_file():
        raise FileNotFoundError(f"dataset index not found: {path} (build it with `vnc-warp dataset`)")
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable index ({exc})") from exc
    if not isinstance(index, dict) or index.get("format") != DATASET_FORMAT or not isinstance(index.get("shapes"), list):
        raise DatasetError(f"{path}: not a {DATASET_FORMAT!r} index")
    return index


def _near_points(mesh: Mesh, count: int, noise: Sequence[float], rng: np.random.Generator) -> list[np.ndarray]:
    """``count`` surface points displaced by Gaussian noise, split evenly over the ``noise`` levels."""
    per_level = np.diff(np.linspace(0, count, len(noise) + 1).round().astype(int))
    parts = []
    for sigma, n in zip(noise, per_level):
        pts, _ = sample_surface(mesh, int(n), rng)
        parts.append(pts + rng.normal(0.0, sigma, size=pts.shape))
    return parts


def _sample_stage(mesh: Mesh, rng: np.random.Generator, *, num_surface: int, num_uniform: int, num_near: int,
                  noise: Sequence[float], truncation: float, device: wp.context.Device, reference: Mesh | None = None,
                  num_reference: int = 0, grid_resolution: int = 0) -> dict[str, np.ndarray]:
    """Surface points, queries and truncated signed distances of one normalized stage mesh.

    Queries: ``num_uniform`` uniform in the box and ``num_reference`` near ``reference`` (the trajectory's
    stage 0), both flagged far; then ``num_near`` near the stage's own surface, flagged near. With
    ``grid_resolution`` R, also ``grid``: the TSDF at the nodes of ``linspace(-1, 1, R)^3``, indexed [x, y, z].
    """
    surf, normals = sample_surface(mesh, num_surface, rng)
    parts = [rng.uniform(-1.0, 1.0, size=(num_uniform, 3))]
    if num_reference:
        parts += _near_points(reference, num_reference, noise, rng)
    far = sum(len(p) for p in parts)
    parts += _near_points(mesh, num_near, noise, rng)
    queries = np.concatenate(parts).astype(np.float32)
    # The labels stay on the device from Warp to PyTorch: torch in, torch out (no host round trip).
    q = torch.from_numpy(queries).to(wp.device_to_torch(device))
    sd = signed_distance(mesh, q, device=device, max_dist=truncation, sign="winding")
    tsdf = torch.clamp(sd, -truncation, truncation)
    near = np.zeros(queries.shape[0], dtype=bool)
    near[far:] = True
    arrays = {
        "surface": np.concatenate([surf, normals], axis=1).astype(np.float32),
        "queries": queries,
        "tsdf": tsdf.cpu().numpy(),
        "near": near,
    }
    if grid_resolution:
        axis = torch.linspace(-1.0, 1.0, grid_resolution, device=q.device)
        nodes = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3).contiguous()
        sd = signed_distance(mesh, nodes, device=device, max_dist=truncation, sign="winding")
        arrays["grid"] = torch.clamp(sd, -truncation, truncation).reshape((grid_resolution,) * 3).cpu().numpy()
    return arrays


def build_dataset(
    traj_dirs: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    num_surface: int = 16384,
    num_uniform: int = 16384,
    num_near: int = 16384,
    noise: Sequence[float] = (0.005, 0.02),
    truncation: float = 0.1,
    num_reference: int = 0,
    grid_resolution: int = 0,
    device=None,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Sample every listed stage of every trajectory into ``out_dir`` (written once, read many times).

    Per stage: ``num_surface`` area-weighted surface points with face normals, ``num_uniform`` queries
    uniform in [-1, 1]^3, ``num_reference`` queries near the trajectory's stage-0 surface and ``num_near``
    queries near the stage's own surface (surface points plus Gaussian noise, split evenly over the ``noise``
    standard deviations), labelled with the stage's signed distances (:func:`vnc_warp.sdf.signed_distance`,
    winding-number sign, negative inside) clamped to ``[-truncation, truncation]``; all lengths in normalized
    units (see :func:`normalization`). The C-VAEs decode every stage from stage 0's encoding, so the space the
    detailed input filled and a later stage left is where their remnants of it float; the ``num_reference``
    queries supervise it. Only the own-surface queries are flagged ``near``. With ``grid_resolution`` R, the
    TSDF on an R^3 grid over [-1, 1]^3 too, from which items label fresh uniform queries
    (:class:`TrajectoryDataset`, ``fresh_fraction``), so that the far field is not a fixed set of points.

    A stage whose file already exists, loads, matches its checksum in ``index.json`` and was produced
    by the same settings, normalization and stage mesh is skipped; a corrupt or stale one is rebuilt
    (with a warning). Shapes already in ``index.json`` but not in ``traj_dirs`` are kept.

    Args:
        traj_dirs: trajectory directories; the directory name is the shape name (must be unique).
        out_dir: dataset directory (created).
        num_surface, num_uniform, num_near: samples per stage.
        num_reference: queries per stage near the trajectory's stage 0 (flagged far).
        grid_resolution: nodes per axis of the stored TSDF grid (0: none).
        noise: near-surface noise standard deviations (normalized units), e.g. two levels.
        truncation: TSDF truncation distance (normalized units).
        device: Warp device for the signed distances (None: preferred device).
        seed: base seed; stage ``i`` of shape ``name`` draws from ``(seed, crc32(name), i)``.
        overwrite: allow ``out_dir`` to have been built with different settings (its samples are rebuilt).
        progress: show a tqdm progress bar.

    Returns:
        ``{"index": path of index.json, "built": n, "skipped": n, "rebuilt": n, "shapes": n}``.

    Raises:
        ValueError: bad settings, duplicate shape names, or ``out_dir`` built with other settings
            (unless ``overwrite``).
        DatasetError / TrajectoryError / FileNotFoundError / MeshError: unusable trajectories or samples (named
            in the message), e.g. stage files their manifest does not own or that fail their checksum, or samples
            with NaN.
        OSError: ``out_dir`` cannot be created or written to (checked before anything else).
    """
    from tqdm.auto import tqdm

    if min(num_surface, num_near) < 1 or num_uniform < 0:
        raise ValueError(f"build_dataset: sample counts must be positive, got surface={num_surface}, "
                         f"uniform={num_uniform}, near={num_near}")
    noise = [float(s) for s in noise]
    if not noise or min(noise) <= 0.0 or len(noise) > num_near:
        raise ValueError(f"build_dataset: noise must list positive standard deviations, got {noise}")
    if not truncation > 0.0:
        raise ValueError(f"build_dataset: truncation must be positive, got {truncation}")
    if num_reference < 0:
        raise ValueError(f"build_dataset: num_reference must be >= 0, got {num_reference}")
    config = {"num_surface": int(num_surface), "num_uniform": int(num_uniform), "num_near": int(num_near),
              "noise": noise, "truncation": float(truncation), "seed": int(seed)}
    if num_reference:
        config["num_reference"] = int(num_reference)
    if grid_resolution:
        if grid_resolution < 2:
            raise ValueError(f"build_dataset: grid_resolution must be 0 or >= 2, got {grid_resolution}")
        config["grid_resolution"] = int(grid_resolution)
    out = output_dir(out_dir, what="dataset folder")
    trajs = [read_trajectory(d) for d in traj_dirs]
    names = [tr.name for tr in trajs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"build_dataset: trajectory directory names must be unique, repeated: {dup}")
    shapes: dict[str, dict] = {}
    if (out / "index.json").is_file():
        try:
            old = _read_index(out)
        except DatasetError as exc:
            warnings.warn(f"{exc}; rebuilding the index", stacklevel=2)
            old = None
        if old is not None:
            if old.get("config") != config and not overwrite:
                raise ValueError(f"{out} was built with other settings {old.get('config')} (now {config}); "
                                 "use another directory or overwrite=True (--overwrite)")
            if old.get("config") == config:
                shapes = {s["name"]: s for s in old["shapes"]}
    dev = get_device(device)
    counts = {"built": 0, "skipped": 0, "rebuilt": 0}
    bar = tqdm(total=sum(len(tr.stages) for tr in trajs), unit="stage", disable=not progress, desc="dataset")
    for tr in trajs:
        stage0 = tr.load_stage(0)
        center, scale = normalization(stage0)
        reference = stage0.with_vertices((stage0.vertices.astype(np.float64) - center) * scale)
        known = {st["file"]: st.get("sha256") for st in shapes.get(tr.name, {}).get("stages", [])}
        entries = []
        for pos, st in enumerate(tr.stages):
            rel = f"{tr.name}/stage_{st.index:03d}.npz"
            path = out / rel
            stage_config = dict(config, center=center.tolist(), scale=scale, t=st.t, index=st.index,
                                source_sha256=st.sha256 or _sha256(st.path))
            sha, stale = None, False
            if path.is_file():
                try:
                    arrays = _read_sample(path, known.get(rel))
                    if json.loads(str(arrays["config"])) == stage_config:
                        sha = known.get(rel) or _sha256(path)
                    else:
                        stale = True
                except ValueError as exc:  # DatasetError, or an unparsable config string
                    warnings.warn(f"rebuilding: {exc}", stacklevel=2)
                    stale = True
            if sha is None:
                mesh = tr.load_stage(pos)
                mesh = mesh.with_vertices((mesh.vertices.astype(np.float64) - center) * scale)
                rng = np.random.default_rng([int(seed), zlib.crc32(tr.name.encode()), st.index])
                arrays = _sample_stage(mesh, rng, num_surface=num_surface, num_uniform=num_uniform,
                                       num_near=num_near, noise=noise, truncation=truncation, device=dev,
                                       reference=reference, num_reference=num_reference,
                                       grid_resolution=grid_resolution)
                arrays["t"] = np.float32(st.t)
                arrays["config"] = np.array(json.dumps(stage_config))
                _check_finite(arrays, f"{st.path} (sampled for {rel})")
                sha = _write_sample(path, arrays)
                counts["rebuilt" if stale else "built"] += 1
            else:
                counts["skipped"] += 1
            entries.append({"index": st.index, "t": st.t, "file": rel, "sha256": sha})
            bar.update(1)
        shapes[tr.name] = {"name": tr.name, "trajectory": str(tr.root), "source": tr.source,
                           "center": center.tolist(), "scale": scale, "truncation": float(truncation),
                           "stages": entries}
        _write_json(out / "index.json", {"format": DATASET_FORMAT, "config": config,
                                          "shapes": [shapes[k] for k in sorted(shapes)]})
    bar.close()
    return {"index": str(out / "index.json"), "shapes": len(shapes), **counts}


def verify_dataset(root: str | os.PathLike) -> int:
    """Check every sample file of a dataset (checksum, load, keys, shapes).

    Returns:
        The number of files checked.

    Raises:
        DatasetError: listing every bad file and why.
    """
    root = Path(root)
    index = _read_index(root)
    problems, n = [], 0
    for shape in index["shapes"]:
        for st in shape["stages"]:
            n += 1
            try:
                _read_sample(root / st["file"], st.get("sha256"))
            except DatasetError as exc:
                problems.append(str(exc))
    if problems:
        raise DatasetError(f"{len(problems)} of {n} sample file(s) are unusable:\n  " + "\n  ".join(problems))
    return n


class TrajectoryDataset(torch.utils.data.Dataset):
    """Stages of a built dataset as training items with random point subsets.

    Item ``i`` is a dict of tensors: ``surface`` (num_surface, 6) float32 xyz + normal, ``queries``
    (num_queries, 3) float32, ``tsdf`` (num_queries,) float32, ``near`` (num_queries,) bool, ``t`` ()
    float32, ``shape_id`` () int64 (position of the shape in :attr:`shape_names`, the same for every
    split), ``stage`` () int64 and, with ``num_on_surface > 0``, ``on_surface`` (num_on_surface, 6): another
    subset of the stage's own surface samples (for the surface and normal terms; ``surface`` may be replaced
    by stage 0's, :class:`~vnc_warp.training.train.Stage0Input`). The subsets come from a generator seeded by ``(seed, epoch, i)``,
    so items are reproducible, differ across epochs (:meth:`set_epoch`) and are safe in DataLoader
    workers. With ``repeats = k`` every stage appears k times per epoch (item ``i`` is stage
    ``i % n_stages``), each time with its own subsets: small sets then fill a batch, and the
    DataLoader workers are restarted k times less often. Every file is checked against its SHA-256 in ``index.json`` when read; a corrupt one
    raises :class:`DatasetError` and is never returned.

    Args:
        root: dataset directory (with ``index.json``).
        num_surface: surface points per item.
        num_queries: query points per item; ``round(near_fraction * num_queries)`` of them near the surface.
        split: ``"train"`` (all shapes except ``holdout``), ``"test"`` (only ``holdout``) or ``"all"``.
        holdout: shape names held out for generalization tests.
        seed: base seed of the subsets.
        near_fraction: share of near-surface queries per item.
        cache: keep checked arrays in memory after the first read (see :meth:`preload`).
        repeats: passes over the stages per epoch (>= 1).
        num_on_surface: points of ``on_surface`` per item (0: no such key).
        fresh_fraction: share of the far (not near-surface) queries drawn afresh, uniform in [-1, 1]^3, for every
            item and labelled by trilinear interpolation of the stage's TSDF grid (a dataset built with
            ``grid_resolution``); only points at least half the truncation from the surface are kept, where the
            interpolation is exact up to the grid's rounding. A fixed pool leaves gaps a decoder can fill with
            floating surfaces; fresh points close them over the run.
    """

    def __init__(self, root: str | os.PathLike, *, num_surface: int = 2048, num_queries: int = 4096,
                 split: str = "train", holdout: Sequence[str] = (), seed: int = 0, near_fraction: float = 0.5,
                 cache: bool = False, repeats: int = 1, num_on_surface: int = 0, fresh_fraction: float = 0.0):
        self.root = Path(root)
        index = _read_index(self.root)
        if split not in ("train", "test", "all"):
            raise ValueError(f"TrajectoryDataset: split must be 'train', 'test' or 'all', got {split!r}")
        if num_surface < 1 or num_queries < 1 or not 0.0 <= near_fraction <= 1.0:
            raise ValueError("TrajectoryDataset: num_surface and num_queries must be >= 1, near_fraction in [0, 1]")
        if int(repeats) < 1:
            raise ValueError(f"TrajectoryDataset: repeats must be >= 1, got {repeats}")
        self.repeats = int(repeats)
        holdout = (holdout,) if isinstance(holdout, str) else tuple(holdout)
        self.shapes = index["shapes"]
        self.shape_names = [s["name"] for s in self.shapes]
        unknown = sorted(set(holdout) - set(self.shape_names))
        if unknown:
            raise ValueError(f"TrajectoryDataset: holdout names not in {self.root / 'index.json'}: {unknown}")
        keep = {"train": lambda n: n not in holdout, "test": lambda n: n in holdout, "all": lambda n: True}[split]
        self.items = [(sid, st) for sid, s in enumerate(self.shapes) if keep(s["name"]) for st in s["stages"]]
        if not self.items:
            raise ValueError(f"TrajectoryDataset: split {split!r} of {self.root} is empty (holdout={list(holdout)})")
        if int(num_on_surface) < 0:
            raise ValueError(f"TrajectoryDataset: num_on_surface must be >= 0, got {num_on_surface}")
        self.num_surface, self.num_queries, self.num_on_surface = int(num_surface), int(num_queries), int(num_on_surface)
        self.num_near = int(round(near_fraction * num_queries))
        if not 0.0 <= fresh_fraction <= 1.0:
            raise ValueError(f"TrajectoryDataset: fresh_fraction must be in [0, 1], got {fresh_fraction}")
        if fresh_fraction and "grid_resolution" not in index.get("config", {}):
            raise ValueError(f"TrajectoryDataset: fresh_fraction needs a dataset built with a TSDF grid; "
                             f"{self.root / 'index.json'} has none (build it with grid_resolution > 0)")
        self.fresh_fraction = float(fresh_fraction)
        self.seed, self.epoch = int(seed), 0
        self._cache: dict[int, dict[str, np.ndarray]] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.items) * self.repeats

    def item_ids(self) -> list[tuple[int, int]]:
        """``(shape_id, stage)`` of every item, without reading any file."""
        return [(sid, int(st["index"])) for sid, st in self.items] * self.repeats

    def stage_times(self) -> list[float]:
        """``t`` (Eq. 7) of every item, from the index, without reading any file."""
        return [float(st["t"]) for _, st in self.items] * self.repeats

    def item_file(self, shape_id: int, stage: int) -> str:
        """The sample file of a shape's stage (for messages that must say where a value came from)."""
        for st in self.shapes[shape_id]["stages"]:
            if int(st["index"]) == stage:
                return str(self.root / st["file"])
        return f"{self.root}: shape {self.shape_names[shape_id]} stage {stage}"

    def preload(self) -> None:
        """Read and check every sample file into the cache now (``cache=True`` only).

        DataLoader workers forked afterwards share the arrays instead of each reading every file again
        at the start of every epoch.
        """
        if self._cache is None:
            raise ValueError("TrajectoryDataset.preload: the dataset was built with cache=False")
        for i in range(len(self.items)):
            self._arrays(i)

    def set_epoch(self, epoch: int) -> None:
        """Draw new subsets: items depend on ``(seed, epoch, i)``."""
        self.epoch = int(epoch)

    def _arrays(self, i: int) -> dict[str, np.ndarray]:
        i %= len(self.items)
        if self._cache is not None and i in self._cache:
            return self._cache[i]
        st = self.items[i][1]
        try:
            arrays = _read_sample(self.root / st["file"], st.get("sha256"))
        except DatasetError as exc:
            raise DatasetError(f"{exc}; re-run `vnc-warp dataset` on its trajectory to rebuild it") from None
        if self._cache is not None:
            self._cache[i] = arrays
        return arrays

    def surface(self, i: int) -> torch.Tensor:
        """``self[i]["surface"]`` alone, equal to it bit for bit (the first draw of the item's generator), without
        the queries and labels: what an encoder-input wrapper takes from another stage."""
        if not 0 <= i < len(self):
            raise IndexError(f"TrajectoryDataset: index {i} out of range [0, {len(self)})")
        a = self._arrays(i)
        rng = np.random.default_rng([self.seed, self.epoch, int(i)])
        ns = a["surface"].shape[0]
        return torch.from_numpy(np.ascontiguousarray(a["surface"][rng.choice(ns, self.num_surface,
                                                                             replace=ns < self.num_surface)]))

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if not 0 <= i < len(self):
            raise IndexError(f"TrajectoryDataset: index {i} out of range [0, {len(self)})")
        sid, st = self.items[i % len(self.items)]
        a = self._arrays(i)
        rng = np.random.default_rng([self.seed, self.epoch, int(i)])
        ns = a["surface"].shape[0]
        s_idx = rng.choice(ns, self.num_surface, replace=ns < self.num_surface)
        near_pool, far_pool = np.flatnonzero(a["near"]), np.flatnonzero(~a["near"])
        n_near = 0 if near_pool.size == 0 else self.num_queries if far_pool.size == 0 else self.num_near
        n_far = self.num_queries - n_near
        fresh_q, fresh_d = self._fresh(a, int(round(self.fresh_fraction * n_far)), float(self.shapes[sid]["truncation"]),
                                       rng)
        n_pool = n_far - len(fresh_q)
        q_idx = np.concatenate([rng.choice(far_pool, n_pool, replace=far_pool.size < n_pool),
                                rng.choice(near_pool, n_near, replace=near_pool.size < n_near)])
        near = a["near"][q_idx]
        if len(fresh_q):
            near = np.concatenate([np.zeros(len(fresh_q), dtype=bool), near])
        item = {
            "surface": torch.from_numpy(np.ascontiguousarray(a["surface"][s_idx])),
            "queries": torch.from_numpy(np.concatenate([fresh_q, a["queries"][q_idx]])),
            "tsdf": torch.from_numpy(np.concatenate([fresh_d, a["tsdf"][q_idx]])),
            "near": torch.from_numpy(near),
            "t": torch.tensor(float(st["t"]), dtype=torch.float32),
            "shape_id": torch.tensor(sid, dtype=torch.int64),
            "stage": torch.tensor(int(st["index"]), dtype=torch.int64),
        }
        if self.num_on_surface:
            o_idx = rng.choice(ns, self.num_on_surface, replace=ns < self.num_on_surface)
            item["on_surface"] = torch.from_numpy(np.ascontiguousarray(a["surface"][o_idx]))
        return item

    @staticmethod
    def _fresh(a: dict[str, np.ndarray], count: int, truncation: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``count`` uniform points in [-1, 1]^3 at least ``truncation / 2`` from the surface, with their
        TSDF interpolated from ``a["grid"]``: (n, 3) and (n,) float32."""
        if count == 0:
            return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
        from scipy.ndimage import map_coordinates

        grid = a["grid"]
        pts = rng.uniform(-1.0, 1.0, size=(2 * count, 3))
        d = map_coordinates(grid, ((pts + 1.0) * 0.5 * (grid.shape[0] - 1)).T, order=1)
        keep = np.flatnonzero(np.abs(d) >= 0.5 * truncation)[:count]
        return pts[keep].astype(np.float32), d[keep].astype(np.float32)
