"""Surface-reconstruction metrics of Sec. 4.3 / Tab. 2: Chamfer distance, EMD and normal consistency error.

Conventions (all lengths in the normalized units of the ground-truth trajectory: its stage-0 bounding
box maps to a max extent of 1.8, see :func:`vnc_warp.training.data.normalization`):

* **CD** (reported x1e-4): ``mean_a min_b |a - b|^2 + mean_b min_a |a - b|^2`` over ``n_points``
  area-weighted samples of each surface, i.e. the *sum* of the two directional means of *squared*
  nearest-neighbour distances (the PyTorch3D ``chamfer_distance`` convention).
* **EMD** (reported x1e-2): the exact optimal one-to-one assignment
  (``scipy.optimize.linear_sum_assignment``) between ``n_emd`` samples of each surface, reported as
  the *mean Euclidean* (not squared) distance of matched pairs.
* **NCE** (radians): for every sample, the angle between its face normal and the normal of its
  nearest neighbour on the other surface, averaged over both directions. *Oriented* by default
  (``arccos(n1 . n2)`` in [0, pi]; both surfaces are closed and wound outward, so a flipped normal is
  an error of pi); ``oriented=False`` uses ``arccos(|n1 . n2|)`` in [0, pi/2].

Both surfaces are sampled with generators of the same seed, so identical meshes score exactly 0.

Every score is reported in two frames and for two parts of the prediction:

* **frames**: ``package`` (the normalized units above) and ``unit_box`` (the ground truth's stage-0 bounding
  box scaled to a max extent of 1, as most papers do): the same samples, so CD scales by ``1 / 1.8^2``, EMD by
  ``1 / 1.8`` and NCE not at all;
* **parts**: ``all`` (every connected component of the prediction) and ``largest`` (its largest component by
  area): a floating fragment far from the surface can dominate CD, and the two numbers tell it apart from an
  error of the body itself.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vnc_warp.mesh import Mesh, MeshError, load_mesh

from .data import normalization, read_trajectory, sample_surface

# ``unit_box`` over ``package`` lengths: the package frame maps the stage-0 box to a max extent of 1.8
UNIT_BOX = 1.0 / 1.8
FRAMES = ("package", "unit_box")

__all__ = [
    "FRAMES",
    "UNIT_BOX",
    "chamfer_distance",
    "combine_reports",
    "sampling_floors",
    "largest_component",
    "compare_meshes",
    "earth_movers_distance",
    "evaluate_trajectory",
    "normal_consistency_error",
    "read_prediction_dir",
]


def _points(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty (N, 3) array, got shape {a.shape}")
    return a


def _nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest neighbours both ways: ``(d_ab, i_ab, d_ba, i_ba)``, distance and index in ``b`` of each point of
    ``a``'s nearest neighbour and the same from ``b`` into ``a`` (one k-d tree per set, one query each way: CD and
    NCE share them)."""
    from scipy.spatial import cKDTree

    dab, iab = cKDTree(b).query(a)
    dba, iba = cKDTree(a).query(b)
    return dab, iab, dba, iba


def _chamfer(dab: np.ndarray, dba: np.ndarray) -> float:
    """CD from the nearest-neighbour distances of both directions (module docstring)."""
    return float(np.mean(dab**2) + np.mean(dba**2))


def _nce(na: np.ndarray, nb: np.ndarray, iab: np.ndarray, iba: np.ndarray, oriented: bool) -> float:
    """NCE from the nearest-neighbour indices of both directions (module docstring)."""
    def angle(n1, n2):
        dot = np.einsum("ij,ij->i", n1, n2)
        return np.arccos(np.clip(dot if oriented else np.abs(dot), -1.0, 1.0)).mean()

    return float(0.5 * (angle(na, nb[iab]) + angle(nb, na[iba])))


def chamfer_distance(a, b) -> float:
    """Symmetric Chamfer distance: sum of the two mean squared nearest-neighbour distances.

    Args:
        a: (N, 3) points.
        b: (M, 3) points.

    Returns:
        ``mean_i min_j |a_i - b_j|^2 + mean_j min_i |a_i - b_j|^2`` (squared length units).
    """
    a, b = _points(a, "chamfer_distance: a"), _points(b, "chamfer_distance: b")
    dab, _, dba, _ = _nearest(a, b)
    return _chamfer(dab, dba)


def earth_movers_distance(a, b) -> float:
    """Exact EMD between equal-size point sets: mean Euclidean distance of the optimal matching.

    Args:
        a: (N, 3) points.
        b: (N, 3) points (same N; cost O(N^3), keep N to a few thousand).

    Returns:
        ``min_sigma mean_i |a_i - b_sigma(i)|`` (length units).
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    a, b = _points(a, "earth_movers_distance: a"), _points(b, "earth_movers_distance: b")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"earth_movers_distance: point sets must have equal size, got {a.shape[0]} and {b.shape[0]}")
    cost = cdist(a, b)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def normal_consistency_error(a, na, b, nb, *, oriented: bool = True) -> float:
    """Mean angle (radians) between each point's normal and its nearest neighbour's normal, both ways.

    Args:
        a, na: (N, 3) points and unit normals of the first surface.
        b, nb: (M, 3) points and unit normals of the second surface.
        oriented: ``arccos(n1 . n2)`` in [0, pi] (True) or ``arccos(|n1 . n2|)`` in [0, pi/2].

    Returns:
        ``(mean_i angle(na_i, nb_nn(i)) + mean_j angle(nb_j, na_nn(j))) / 2``.
    """
    a, b = _points(a, "normal_consistency_error: a"), _points(b, "normal_consistency_error: b")
    na, nb = np.asarray(na, dtype=np.float64), np.asarray(nb, dtype=np.float64)
    if na.shape != a.shape or nb.shape != b.shape:
        raise ValueError(f"normal_consistency_error: normals {na.shape}, {nb.shape} must match points {a.shape}, {b.shape}")
    _, iab, _, iba = _nearest(a, b)
    return _nce(na, nb, iab, iba, oriented)


class _Surface:
    """Vertices (float64) and faces of any mesh-like input, oriented outward when closed."""

    def __init__(self, mesh: Any, name: str):
        if isinstance(mesh, Mesh):
            v, f = mesh.vertices, mesh.faces
        elif isinstance(mesh, tuple) and len(mesh) == 2:
            v, f = mesh
        elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            v, f = mesh.vertices, mesh.faces
        else:
            raise TypeError(f"{name}: expected a Mesh, trimesh.Trimesh or (vertices, faces), got {type(mesh).__name__}")
        self.vertices = np.asarray(v, dtype=np.float64)
        self.faces = np.asarray(f, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise MeshError(f"{name}: vertices must be (V, 3) and faces (F, 3), got {self.vertices.shape}, {self.faces.shape}")
        v = self.vertices
        tri = v[self.faces] if self.faces.size else np.zeros((0, 3, 3))
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if not np.isfinite(v).all() or not area2.sum() > 0.0:
            raise MeshError(f"{name}: empty or non-finite surface ({v.shape[0]} vertices, {self.faces.shape[0]} faces)")
        # Outward orientation matters for the oriented NCE; the signed volume decides it for closed meshes.
        if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0.0:
            self.faces = self.faces[:, ::-1]


def largest_component(mesh, *, name: str = "mesh") -> tuple[np.ndarray, np.ndarray, int]:
    """The connected component (faces sharing vertices) of largest area.

    Args:
        mesh: a :class:`Mesh`, ``trimesh.Trimesh`` or ``(vertices, faces)``.
        name: for error messages.

    Returns:
        ``(vertices (V', 3) float64, faces (F', 3) int64, number of components of the input)``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    s = _Surface(mesh, name)
    v, f = s.vertices, s.faces
    rows, cols = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    _, label = connected_components(coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(len(v), len(v))),
                                    directed=False)
    face_label = label[f[:, 0]]
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = f[face_label == np.argmax(np.bincount(face_label, weights=area))]
    used, inverse = np.unique(keep, return_inverse=True)
    return v[used], inverse.reshape(-1, 3).astype(np.int64), len(np.unique(face_label))


def _sample(mesh, name: str, n: int, seed: int, normalization=None) -> tuple[np.ndarray, np.ndarray]:
    s = _Surface(mesh, name)
    if normalization is not None:
        s.vertices = (s.vertices - np.asarray(normalization[0], dtype=np.float64)) * float(normalization[1])
    return sample_surface(s, n, np.random.default_rng(seed))


def _scores(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], n_emd: int, oriented: bool) -> dict:
    """CD, EMD and NCE of two samplings in the package frame, with their ``unit_box`` values."""
    (pa, na), (pb, nb) = a, b
    pa, pb = _points(pa, "scores: a"), _points(pb, "scores: b")
    dab, iab, dba, iba = _nearest(pa, pb)
    cd = _chamfer(dab, dba)
    emd = earth_movers_distance(pa[:n_emd], pb[:n_emd])
    nce = _nce(np.asarray(na, dtype=np.float64), np.asarray(nb, dtype=np.float64), iab, iba, oriented)
    return {"cd": cd, "emd": emd, "nce": nce, "cd_x1e4": cd * 1e4, "emd_x1e2": emd * 1e2,
            "unit_box": {"cd_x1e4": cd * 1e4 * UNIT_BOX**2, "emd_x1e2": emd * 1e2 * UNIT_BOX, "nce": nce}}


def _check_counts(n_points: int, n_emd: int) -> None:
    if n_points < 1 or not 1 <= n_emd <= n_points:
        raise ValueError(f"need n_points >= 1 and 1 <= n_emd <= n_points, got {n_points}, {n_emd}")


def compare_meshes(pred, gt, *, n_points: int = 100000, n_emd: int = 4096, seed: int = 0,
                   normalization: tuple[Any, float] | None = None, oriented: bool = True) -> dict:
    """CD, EMD and NCE between two surfaces (conventions in the module docstring).

    Sampling sets a floor under the scores of two *different* samplings of one surface; on a shape
    normalized to extent 1.8 it is about CD 0.5e-4 at 100k points and EMD 5e-2 at 4096 points
    (:func:`evaluate_trajectory` reports it as ``sampling_floor``).

    Args:
        pred: predicted surface (:class:`Mesh`, ``trimesh.Trimesh`` or ``(vertices, faces)``).
        gt: ground-truth surface, same kinds.
        n_points: area-weighted samples per surface for CD and NCE.
        n_emd: samples per surface for the exact EMD (the first ``n_emd`` of the ``n_points``;
            O(n_emd^3) time, about 2 s at 4096).
        seed: sampling seed, the same for both surfaces.
        normalization: ``(center (3,), scale)`` applied to both, ``x -> (x - center) * scale``; None if
            both are already in normalized units.
        oriented: oriented (default) or unoriented NCE.

    Returns:
        ``{"cd", "emd", "nce", "cd_x1e4", "emd_x1e2"}`` as floats.
    """
    _check_counts(n_points, n_emd)
    return _scores(_sample(pred, "pred", n_points, seed, normalization),
                   _sample(gt, "gt", n_points, seed, normalization), n_emd, oriented)


def read_prediction_dir(pred_dir: str | os.PathLike) -> tuple[dict[float, Any], dict]:
    """Read the output of ``vnc-warp generate``: meshes listed with their ``t`` in a JSON file.

    The JSON is ``manifest.json``, ``generate.json`` or the only ``*.json`` in the folder, holding
    either a list of ``{"t": float, "file": str | null}`` or an object with that list under
    ``"meshes"``, ``"stages"`` or ``"samples"`` and optionally ``"frame": "world" | "normalized"``.
    ``"file": null`` marks a time with no mesh (its ``"error"`` is kept).

    Returns:
        ``({t: trimesh.Trimesh or None}, meta)`` where ``meta`` is the JSON object (``{}`` for a bare list).

    Raises:
        FileNotFoundError: no JSON or a listed mesh missing.
        ValueError: a JSON of another layout.
    """
    import trimesh

    root = Path(pred_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"prediction folder not found: {root}")
    path = next((root / n for n in ("manifest.json", "generate.json") if (root / n).is_file()), None)
    if path is None:
        found = sorted(root.glob("*.json"))
        if len(found) != 1:
            raise FileNotFoundError(f"{root}: expected manifest.json, generate.json or exactly one *.json listing "
                                    f"the meshes, found {[p.name for p in found]}")
        path = found[0]
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable JSON ({exc})") from exc
    meta = doc if isinstance(doc, dict) else {}
    items = doc if isinstance(doc, list) else next((doc[k] for k in ("meshes", "stages", "samples")
                                                   if isinstance(doc.get(k), list)), None)
    if not items or not all(isinstance(it, dict) and {"t", "file"} <= it.keys() for it in items):
        raise ValueError(f"{path}: expected a list of {{'t': ..., 'file': ...}} (or under 'meshes')")
    out = {}
    for it in items:
        if it["file"] is None:
            out[float(it["t"])] = None
            continue
        file = root / it["file"]
        if not file.is_file():
            raise FileNotFoundError(f"{path}: lists {it['file']!r}, which does not exist")
        out[float(it["t"])] = trimesh.load(file, process=False, force="mesh")
    return out, meta


def _floor(mesh, n_points: int, n_emd: int, seed: int, norm, oriented: bool, sample=None) -> dict:
    """A ground-truth stage against itself resampled (seed ``seed + 1``) at the same counts: the sampling floor.
    ``sample``: the stage's seed-``seed`` sampling when the caller already drew it."""
    first = sample if sample is not None else _sample(mesh, "gt", n_points, seed, norm)
    return _scores(first, _sample(mesh, "gt", n_points, seed + 1, norm), n_emd, oriented)


def _nearest_stage(gt_t: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(gt_t - t)))


def sampling_floors(gt_traj_dir: str | os.PathLike, times, *, n_points: int = 100000, n_emd: int = 4096,
                    seed: int = 0, oriented: bool = True) -> dict:
    """The sampling floors :func:`evaluate_trajectory` reports, for the ground-truth stages nearest ``times`` and
    stage 0, computed once per trajectory (several predictors scored against one trajectory share them).

    Returns:
        ``{"stages": {stage index (str): scores}, "stage0": scores}``, scores as :func:`compare_meshes` plus
        ``unit_box``.
    """
    _check_counts(n_points, n_emd)
    traj = read_trajectory(gt_traj_dir)
    center, scale = normalization(traj.load_stage(0))
    gt_t = np.array([s.t for s in traj.stages])
    positions = sorted({0, *(_nearest_stage(gt_t, float(t)) for t in times)})
    floors = {pos: _floor(load_mesh(traj.stages[pos].path), n_points, n_emd, seed, (center, scale), oriented)
              for pos in positions}
    keep = _SCORE_KEYS + ("unit_box",)
    return {"stages": {str(traj.stages[pos].index): {k: f[k] for k in keep} for pos, f in floors.items()},
            "stage0": {k: floors[0][k] for k in keep}}


def evaluate_trajectory(pred_meshes_by_t: Mapping[float, Any], gt_traj_dir: str | os.PathLike, *,
                        pred_frame: str = "world", n_points: int = 100000, n_emd: int = 4096, seed: int = 0,
                        oriented: bool = True, max_dt: float | None = None, floors: bool = True) -> dict:
    """Compare predicted meshes at times ``t`` with the ground-truth VNC-Flow stages (Tab. 2 metrics).

    Each prediction is matched to the GT stage with the nearest ``t`` (Eq. (7)); both are normalized
    with the GT stage-0 normalization. Works for any predictor (C-VAE, latent interpolation, ...).

    Args:
        pred_meshes_by_t: ``{t: mesh}`` (:class:`Mesh`, ``trimesh.Trimesh`` or ``(vertices, faces)``;
            None for a time where the predictor produced no mesh).
        gt_traj_dir: a trajectory directory (``manifest.json`` + stage meshes).
        pred_frame: ``"world"`` (predictions in the GT's original units) or ``"normalized"`` (already in
            the normalized frame, e.g. raw decoder output).
        n_points, n_emd, seed, oriented: see :func:`compare_meshes`.
        max_dt: if set, a prediction whose nearest GT stage is farther than this in ``t`` is an error.
        floors: compute the sampling floors (``floor`` of each entry, ``sampling_floor``); False leaves them out
            (None), for a caller that takes them from :func:`sampling_floors` once per trajectory.

    Returns:
        ``{"gt", "normalization", "conventions", "per_t": [...], "mean": {...}, "failed": n,
        "sampling_floor": {...}}``; each ``per_t`` entry has ``t``, ``t_gt``, ``stage``, ``components`` (of the
        prediction) and the :func:`compare_meshes` numbers of the whole prediction (``cd_x1e4``, ``emd_x1e2``,
        ``nce`` in the package frame and under ``unit_box``) and, under ``largest``, those of its largest
        component, and ``floor``: the scored GT stage against itself sampled with seed ``seed + 1`` at the same
        counts (what a perfect prediction would get); or an ``error`` message for a prediction that could not be
        scored (excluded from ``mean``). ``sampling_floor`` is that floor for GT stage 0.
    """
    if pred_frame not in ("world", "normalized"):
        raise ValueError(f"evaluate_trajectory: pred_frame must be 'world' or 'normalized', got {pred_frame!r}")
    if not pred_meshes_by_t:
        raise ValueError("evaluate_trajectory: no predicted meshes")
    _check_counts(n_points, n_emd)
    traj = read_trajectory(gt_traj_dir)
    stage0 = traj.load_stage(0)
    center, scale = normalization(stage0)
    gt_t = np.array([s.t for s in traj.stages])
    per_t, gt_cache, floor_of = [], {}, {}
    for t in sorted(pred_meshes_by_t, reverse=True):
        pos = _nearest_stage(gt_t, t)
        if max_dt is not None and abs(gt_t[pos] - t) > max_dt:
            raise ValueError(f"evaluate_trajectory: no GT stage within {max_dt} of t = {t} "
                             f"(nearest t = {gt_t[pos]:.4f}, stage {traj.stages[pos].index})")
        entry = {"t": float(t), "t_gt": float(gt_t[pos]), "stage": traj.stages[pos].index}
        if pred_meshes_by_t[t] is None:
            entry["error"] = "no predicted mesh"
            per_t.append(entry)
            continue
        name = f"prediction at t={t}"
        norm = (center, scale) if pred_frame == "world" else None
        try:
            pred = _sample(pred_meshes_by_t[t], name, n_points, seed, norm)
            largest = largest_component(pred_meshes_by_t[t], name=name)
        except MeshError as exc:
            entry["error"] = str(exc)
            per_t.append(entry)
            continue
        if pos not in gt_cache:
            gt_mesh = load_mesh(traj.stages[pos].path)
            gt_cache[pos] = _sample(gt_mesh, "gt", n_points, seed, (center, scale))
            if floors:
                floor_of[pos] = _floor(gt_mesh, n_points, n_emd, seed, (center, scale), oriented, gt_cache[pos])
        entry["components"] = largest[2]
        if floors:
            entry["floor"] = {k: floor_of[pos][k] for k in _SCORE_KEYS + ("unit_box",)}
        entry.update(_scores(pred, gt_cache[pos], n_emd, oriented))
        entry["largest"] = (_scores(_sample(largest[:2], name, n_points, seed, norm), gt_cache[pos], n_emd, oriented)
                            if largest[2] > 1 else {k: entry[k] for k in _SCORE_KEYS + ("unit_box",)})
        per_t.append(entry)
    if not floors:
        floor = None
    elif 0 in floor_of:
        floor = floor_of[0]
    else:
        floor = _floor(stage0, n_points, n_emd, seed, (center, scale), oriented)
    return {
        "gt": str(traj.root),
        "normalization": {"center": center.tolist(), "scale": scale},
        "conventions": {
            "cd": "sum of both directional means of squared nearest-neighbour distances, normalized units, x1e-4",
            "emd": "exact assignment, mean Euclidean distance of matched pairs, normalized units, x1e-2",
            "nce": f"mean nearest-neighbour normal angle, both directions, {'oriented' if oriented else 'unoriented'}, radians",
            "frames": "package: the GT stage-0 box at max extent 1.8; unit_box: the same box at max extent 1",
            "largest": "the prediction's largest connected component by area (the rest dropped)",
            "n_points": n_points, "n_emd": n_emd, "seed": seed, "pred_frame": pred_frame,
        },
        "per_t": per_t,
        **_summary(per_t),
        "sampling_floor": None if floor is None else {k: floor[k] for k in _SCORE_KEYS + ("unit_box",)},
    }


def _summary(per_t: list[dict]) -> dict:
    """``mean`` (whole prediction, and ``largest``) over the scored entries and the ``failed`` count."""
    ok = [e for e in per_t if "error" not in e]
    mean = _mean_scores(ok)
    mean["largest"] = _mean_scores([e["largest"] for e in ok])
    return {"mean": mean, "failed": len(per_t) - len(ok)}


def combine_reports(reports: list[dict]) -> dict:
    """One :func:`evaluate_trajectory` report from reports of one trajectory, each scoring its own times (jobs
    split by ``t``): ``per_t`` joined (``t`` descending), ``mean`` and ``failed`` over all of them, the rest from
    the first report (``sampling_floor``: the first one that has it)."""
    if not reports or len({r["gt"] for r in reports}) != 1:
        raise ValueError("combine_reports: need reports of one trajectory")
    per_t = sorted((e for r in reports for e in r["per_t"]), key=lambda e: -e["t"])
    floor = next((r["sampling_floor"] for r in reports if r.get("sampling_floor") is not None), None)
    return {**reports[0], "per_t": per_t, **_summary(per_t), "sampling_floor": floor}


_SCORE_KEYS = ("cd_x1e4", "emd_x1e2", "nce")


def _mean_scores(entries: list[dict]) -> dict:
    """Means of the reported scores (package frame and ``unit_box``) over scored entries; NaN when none."""
    def mean(values):
        return float(np.mean(values)) if values else math.nan

    out = {k: mean([e[k] for e in entries]) for k in _SCORE_KEYS}
    out["unit_box"] = {k: mean([e["unit_box"][k] for e in entries]) for k in _SCORE_KEYS}
    return out
