"""Benchmark of the VNC operator, its multi-scale analysis and VNC-Flow, with its baselines side by side.

One process, one device; every row is timed the same way: a warm-up call (kernel compilation, caches), then
``n`` calls each bracketed by a device synchronisation, reporting the median and the spread. Rows on the same
mesh and scale carry a ratio against this package's row they compete with (``ratio = row / reference``; above
1 means the package is faster). A row that fails, or would take too long, is reported as such, never crashes
the run. The JSON (``--out``) holds the device, versions, mesh sizes, every row and the goals of the issues,
with a Markdown copy of the tables beside it.

Every row is also set beside the same row of an earlier run (``--baseline``, by default
``docs/results/bench_h200.json``): its median there and the quotient, so that one run says whether anything got
slower; the goals list the rows more than 3 % slower than the baseline.

    python -m bench.vnc --device cuda:0 --meshes meshes --out results/   # the full GPU run (about 6 minutes)
    python -m bench.vnc --device cpu --quick                    # a CPU smoke run (well under a minute)
    python -m bench.vnc --device cpu --sizes 10k --sections eq1 # Eq. (1) against trimesh on spot.obj
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import io
import json
import os
import platform
import re
import sys
import tempfile
import threading
import time
import traceback
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import warp as wp

import vnc_warp as vw
from vnc_warp._device import get_device
from vnc_warp.tuning import Tuning

vflow = importlib.import_module("vnc_warp.flow")  # the module; `vnc_warp.flow` the attribute is the function

# the real meshes: a folder `meshes/` at the repository's root (a GPU machine's copy), else ../shared/data/meshes
_REPO = Path(__file__).resolve().parents[1]
MESH_DIR = next((d for d in (_REPO / "meshes", _REPO.parent / "shared" / "data" / "meshes") if d.is_dir()),
                _REPO.parent / "shared" / "data" / "meshes")
BASELINE = Path(__file__).resolve().parents[1] / "docs" / "results" / "bench_h200.json"

# size name -> (file, trimesh subdivisions); subdivided meshes show how cost grows with V
SIZES = {
    "3k": ("spot_lowres.obj", 0),
    "10k": ("spot.obj", 0),
    "15k": ("armadillo.obj", 0),
    "50k": ("nefertiti.obj", 0),
    "50k-koala": ("koala.obj", 0),
    "200k": ("nefertiti.obj", 1),
    "800k": ("nefertiti.obj", 2),
    "30k-hammer": ("hammer.obj", 0),
}
SECTIONS = ("operator", "scale", "eq1", "flow", "trajectory")
# scales: multiples of the mean edge length l, or fractions of the bounding-box diagonal
TAUS = (("2 l", 2.0, "l"), ("4 l", 4.0, "l"), ("8 l", 8.0, "l"), ("16 l", 16.0, "l"), ("32 l", 32.0, "l"),
        ("diag/8", 0.125, "d"), ("diag/4", 0.25, "d"), ("diag/2", 0.5, "d"))
QUICK_TAUS = (("2 l", 2.0, "l"), ("8 l", 8.0, "l"), ("diag/2", 0.5, "d"))
# rows whose expected work exceeds these are skipped (the time would be spent on one row); pairs = vertex x edge
LIMITS = {
    "cuda": {"bvh": 2e9, "grid": 3e11, "dense": 5e11, "torch": 6e10, "grad": 5e10, "multi": 5e10},
    "cpu": {"bvh": 3e7, "grid": 3e8, "dense": 2e9, "torch": 1e9, "grad": 3e7, "multi": 1e8},
    "quick": {"bvh": 3e6, "grid": 3e7, "dense": 3e7, "torch": 3e7, "grad": 1e7, "multi": 3e7},
}
# Eq. (1) against trimesh runs on these sizes only (trimesh takes seconds per call)
EQ1_SIZES = ("3k", "10k", "50k")
# every strategy and the PyTorch baseline on these sizes; the others (growth with V) get the package's own rows
FULL_SIZES = ("3k", "10k", "50k", "50k-koala")


# --- timing -----------------------------------------------------------------------------------------------------------


def _synchronize(device: wp.Device) -> None:
    wp.synchronize_device(device)
    if device.is_cuda:
        import torch

        if torch.cuda.is_available():
            torch.cuda.synchronize()


def measure(fn, device: wp.Device, *, target_s: float, max_repeats: int, min_repeats: int = 3,
            warmup: bool = True) -> dict:
    """A warm-up call, then ``n`` synchronised calls (``n`` from the first timed call and ``target_s``)."""
    warmup_s = None
    if warmup:
        _synchronize(device)
        t0 = time.perf_counter()
        fn()
        _synchronize(device)
        warmup_s = time.perf_counter() - t0
    times = []
    n = max_repeats
    while len(times) < n:
        _synchronize(device)
        t0 = time.perf_counter()
        fn()
        _synchronize(device)
        times.append(time.perf_counter() - t0)
        if len(times) == 1:
            n = int(np.clip(target_s / max(times[0], 1e-6), min_repeats, max_repeats))
    t = np.array(times) * 1e3
    q25, q75 = np.percentile(t, [25, 75])
    med = float(np.median(t))
    return {"median_ms": med, "min_ms": float(t.min()), "max_ms": float(t.max()),
            "iqr_pct": float(100 * (q75 - q25) / med),
            "repeats": len(times), "warmup_ms": None if warmup_s is None else warmup_s * 1e3}


def spin(fn, device: wp.Device, seconds: float) -> None:
    """Call ``fn`` for ``seconds`` (synchronised, untimed) so the device leaves its idle clocks before timing."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        fn()
        _synchronize(device)


def peak_bytes(fn, device: wp.Device) -> int | None:
    """Peak Warp allocation on ``device`` during one call (``wp.ScopedMemoryTracker``), None if unreadable.

    The engines keep their scratch buffers between calls and replay repeated calls from graphs over scratch of
    their own: ``fn`` should run on a fresh engine without replay (``vw.Engine(mesh, device, Tuning(replay=()))``),
    so that it allocates, and is charged for, all of its memory (a replayed call holds the same scratch)."""
    _synchronize(device)
    out = io.StringIO()
    with wp.ScopedMemoryTracker("bench", print=False) as tracker:
        tracker.clear()
        fn()
        _synchronize(device)
        tracker.report(file=out)
    units = {"B": 1, "KB": 1 << 10, "MB": 1 << 20, "GB": 1 << 30, "TB": 1 << 40}
    text = out.getvalue()
    block = text.split("Peak usage:", 1)[1] if "Peak usage:" in text else ""
    m = re.search(rf"^\s*{re.escape(device.alias)}\s+([\d.]+) ([KMGT]?B)\s*$", block, re.MULTILINE)
    return int(float(m.group(1)) * units[m.group(2)]) if m else None


def gpu_profile(fn, device: wp.Device) -> dict:
    """GPU time of one call by activity (``wp.timing_begin``): total, and the five longest kernels/copies in ms."""
    if not device.is_cuda:
        return {}
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    fn()
    results = wp.timing_end()
    per = {}
    for r in results:
        name = re.sub(r"_[0-9a-f]{8}$", "", r.name.replace("forward kernel ", ""))
        per[name] = per.get(name, 0.0) + r.elapsed
    top = dict(sorted(per.items(), key=lambda kv: -kv[1])[:5])
    return {"gpu_busy_ms": float(sum(per.values())), "gpu_top_ms": {k: round(v, 4) for k, v in top.items()}}


# --- rows -------------------------------------------------------------------------------------------------------------


@dataclass
class Row:
    """One measurement. ``ratio`` = this row's median / the median of row ``ratio_to`` (same mesh and scale)."""

    section: str
    mesh: str
    name: str
    variant: str
    tau_label: str = ""
    tau: float | None = None
    status: str = "ok"
    median_ms: float | None = None
    min_ms: float | None = None
    max_ms: float | None = None
    iqr_pct: float | None = None
    repeats: int = 0
    warmup_ms: float | None = None
    ratio: float | None = None
    ratio_to: str | None = None
    note: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{self.name}[{self.variant}]"


class Bench:
    """Runs the sections, keeps the rows, writes JSON and Markdown after every section."""

    def __init__(self, args):
        self.args = args
        self.device = get_device(args.device)
        self.kind = "cuda" if self.device.is_cuda else "cpu"
        self.limits = LIMITS["quick" if args.quick else self.kind]
        self.start = time.perf_counter()
        self.deadline = self.start + 60.0 * args.max_minutes
        self.rows: list[Row] = []
        self.meshes: dict[str, dict] = {}
        self.target_s = 0.05 if args.quick else (0.2 if self.device.is_cuda else 1.0)
        self.max_repeats = 2 if args.quick else 20
        self.min_repeats = 1 if args.quick else 3
        self.baseline, self.baseline_note = load_baseline(args.baseline, self.device)
        # a GPU left idle runs its first calls at low clocks: the first row of the H200 A/B at 2094192 timed 11 %
        # slower than the same call later in the run; one spin before the first timed row brings the clocks up
        self.spin_s = 1.0 if self.device.is_cuda and not args.quick else 0.0

    # time budget: the trajectory keeps a reserve, every other section stops at the reserve
    def time_left(self, reserve: float = 0.0) -> float:
        return self.deadline - reserve - time.perf_counter()

    @property
    def reserve(self) -> float:
        if "trajectory" not in self.args.sections:
            return 0.0
        return min(120.0, 0.35 * 60.0 * self.args.max_minutes)

    def run(self, row: Row, fn, *, skip: str | None = None, reference: Row | None = None, check=None,
            repeats: int | None = None, warmup: bool = True) -> Row:
        """Time ``fn`` into ``row`` unless ``skip`` says why not; ``check()`` adds fields after timing;
        ``repeats`` caps the timed calls (slow baselines)."""
        self.rows.append(row)
        if skip is None and self.time_left(self.reserve) <= 0:
            skip = "time budget (--max-minutes) used up"
        if skip is not None:
            row.status, row.note = "skipped", skip
            return row
        try:
            if self.spin_s > 0.0:
                spin(fn, self.device, self.spin_s)
                self.spin_s = 0.0
            stats = measure(fn, self.device, target_s=self.target_s, max_repeats=repeats or self.max_repeats,
                            min_repeats=min(self.min_repeats, repeats or self.min_repeats), warmup=warmup)
            for k, v in stats.items():
                setattr(row, k, v)
            if reference is not None and reference.status == "ok" and reference.median_ms:
                row.ratio, row.ratio_to = row.median_ms / reference.median_ms, reference.key
            if check is not None:
                row.extra.update(check())
        except Exception as exc:  # a failing row is a result, not the end of the run
            row.status = "error"
            row.note = f"{type(exc).__name__}: {exc}"[:300]
            row.extra["traceback"] = traceback.format_exc()[-2000:]
        self._print(row)
        return row

    def _print(self, row: Row) -> None:
        if self.args.verbose:
            print(_format_row(row), flush=True)


def _format_row(r: Row) -> str:
    t = "-" if r.median_ms is None else f"{r.median_ms:10.3f}"
    spread = "" if r.iqr_pct is None else f"{r.iqr_pct:5.1f}%"
    ratio = "" if r.ratio is None else f"{r.ratio:8.2f}x"
    base = r.extra.get("baseline_ms")
    before = "" if base is None else f"{base:10.3f}"
    vs = r.extra.get("vs_baseline")
    verdict = "" if vs is None else f"{vs:6.3f}{' SLOWER' if vs > SLOWER else ''}"
    note = r.note if r.status == "ok" else f"{r.status.upper()}: {r.note}"
    extra = ", ".join(f"{k}={_short(v)}" for k, v in r.extra.items()
                      if k not in ("traceback", "baseline_ms", "vs_baseline"))
    return (f"{r.mesh[:14]:14s} {r.tau_label:7s} {r.name[:26]:26s} {r.variant[:13]:13s} {t:>10s} {spread:>6s} "
            f"{ratio:>9s} {before:>10s} {verdict:>13s}  {note} {extra}").rstrip()


# a row this much slower than the same row of the baseline run counts as slower (issue 22: within 3 %)
SLOWER = 1.03


def load_baseline(path, device: wp.Device) -> tuple[dict, str]:
    """The rows of an earlier run (``--baseline``) by ``(mesh, scale, name, variant)``, when it ran on a device of the
    same name; else none, and why."""
    if not path:
        return {}, "no baseline"
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        return {}, f"baseline {path} unreadable ({type(exc).__name__})"
    name = doc.get("device", {}).get("name")
    if name != device.name:
        return {}, f"baseline {path} ran on {name}, this run on {device.name}: not compared"
    rows = {(r["mesh"], r["tau_label"], r["name"], r["variant"]): r for r in doc.get("rows", [])
            if r.get("status") == "ok" and r.get("median_ms")}
    return rows, f"baseline {path} ({doc.get('date', '?')[:10]}, {len(rows)} rows)"


def compare_baseline(b: Bench) -> None:
    """Each row beside the same row of the baseline: ``extra["baseline_ms"]`` and ``extra["vs_baseline"]`` (this
    median / the baseline's; above :data:`SLOWER` the row got slower)."""
    for r in b.rows:
        old = b.baseline.get((r.mesh, r.tau_label, r.name, r.variant))
        if old is not None and r.status == "ok" and r.median_ms:
            r.extra["baseline_ms"] = old["median_ms"]
            r.extra["vs_baseline"] = r.median_ms / old["median_ms"]


def _short(v):
    if isinstance(v, float):
        return f"{v:.3g}"
    return v


# --- meshes -----------------------------------------------------------------------------------------------------------


def load_size(name: str, mesh_dir: Path, allow_large: bool) -> vw.Mesh:
    if name not in SIZES:
        raise ValueError(f"unknown size {name!r}; choose from {', '.join(SIZES)}")
    file, subdiv = SIZES[name]
    path = mesh_dir / file
    if not path.exists():
        if name == "3k":  # the bundled copy of Spot keeps the quick mode self-contained
            from vnc_warp.data import mesh_path

            path = Path(mesh_path("spot"))
        else:
            raise FileNotFoundError(f"{path} not found (pass --meshes DIR)")
    mesh = vw.load_mesh(path)
    if subdiv:
        if not allow_large:
            raise ValueError(f"size {name} (subdivided) is only run on CUDA")
        tm = mesh.to_trimesh()
        for _ in range(subdiv):
            tm = tm.subdivide()
        mesh = vw.load_mesh(tm)
        mesh.name = f"{Path(file).stem}-sub{subdiv}"
    else:
        mesh.name = Path(file).stem
    return mesh


def mesh_info(mesh: vw.Mesh, size: str) -> dict:
    return {"name": mesh.name, "size": size, "vertices": mesh.num_vertices, "faces": int(mesh.faces.shape[0]),
            "interior_edges": int(mesh.topology.num_interior), "mean_edge_length": mesh.mean_edge_length,
            "bbox_diagonal": mesh.bbox_diagonal, "area": mesh.area()}


def pairs_in_reach(V: int, E: int, area: float, tau) -> float:
    """Expected vertex-edge pairs within the cut-off from the surface density: ``sum_k min(E, E pi tau_k^2 / A)``."""
    t = np.broadcast_to(np.asarray(tau, dtype=np.float64), (V,))
    return float(np.minimum(1.0, np.pi * t * t / max(area, 1e-30)).sum() * E)


# --- sections ---------------------------------------------------------------------------------------------------------


def operator_section(b: Bench, mesh: vw.Mesh, info: dict, taus, full: bool) -> None:
    """VNC-soft (``full``: every strategy and the dense PyTorch Eq. (3)), VNC-hard and a backward pass, per scale."""
    dev, lim = b.device, b.limits
    V, E, A = info["vertices"], info["interior_edges"], info["area"]
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=dev)
    torch_dev, torch_why = _torch_device(dev)
    for label, value, unit in taus:
        tau = value * (info["mean_edge_length"] if unit == "l" else info["bbox_diagonal"])
        pairs = pairs_in_reach(V, E, A, tau)
        common = dict(section="operator", mesh=mesh.name, tau_label=label, tau=tau)
        skip = None if pairs <= lim["grid"] else f"~{pairs:.2g} pairs in reach"
        ref = b.run(Row(name="vnc_soft", variant="auto", **common),
                    lambda: vw.vnc_soft(mesh, tau, device=dev), skip=skip,
                    check=lambda: {"chosen": vw.choose_strategy(mesh, tau, device=dev), "pairs_in_reach": pairs})
        if ref.status == "ok" and not b.args.quick:
            fresh = vw.Engine(mesh, dev, Tuning(replay=()))  # no scratch yet, nothing replayed
            fresh.x, fresh.edges  # the mesh's own arrays (kept by every engine) are not the call's
            nbytes = _safe(lambda: peak_bytes(lambda: fresh.vnc_soft(tau), dev))
            if nbytes:
                ref.extra["peak_MB"] = nbytes / 2**20
                ref.extra["bytes_per_V+E"] = nbytes / (V + E)
            ref.extra.update(_safe(lambda: gpu_profile(lambda: vw.vnc_soft(mesh, tau, device=dev), dev)) or {})
        # the same call with the positions given as a device array (a flow step): planned once, then replayed
        b.run(Row(name="vnc_soft", variant="positions", note="positions=wp.array: planned once, replayed",
                  **common), lambda: vw.vnc_soft(mesh, tau, positions=x), skip=skip, reference=ref)
        for strategy in ("grid", "dense", "bvh") if full else ():
            limit = lim[strategy]
            work = V * E if strategy == "dense" else pairs
            b.run(Row(name="vnc_soft", variant=strategy, **common),
                  lambda s=strategy: vw.vnc_soft(mesh, tau, device=dev, strategy=s),
                  skip=None if work <= limit else f"~{work:.2g} pairs for this strategy", reference=ref,
                  repeats=3 if strategy == "bvh" else None)
        hard_pairs = pairs_in_reach(V, E, A, tau + 0.5 * info["mean_edge_length"])
        hard = b.run(Row(name="vnc_hard", variant="auto", **common), lambda: vw.vnc_hard(mesh, tau, device=dev),
                     skip=None if hard_pairs <= lim["grid"] else f"~{hard_pairs:.2g} pairs in reach", reference=ref,
                     check=lambda: {"chosen": vw.choose_strategy(mesh, tau, variant="hard", device=dev)})
        _torch_rows(b, mesh, tau, common, ref, hard, torch_dev, torch_why, full)


def _torch_device(dev: wp.Device):
    try:
        import torch
    except ImportError:
        return None, "torch is not installed"
    if dev.is_cuda:
        if not torch.cuda.is_available():
            return None, "this torch build has no CUDA"
        return torch.device(f"cuda:{dev.ordinal}"), None
    return torch.device("cpu"), None


def _torch_rows(b: Bench, mesh, tau, common, ref: Row, hard: Row, torch_dev, torch_why, full: bool) -> None:
    """The dense PyTorch Eq. (3) (``full``), and the torch ops: VNC-soft forward, forward + backward, and VNC-hard
    forward + backward (against the Warp forwards ``ref`` and ``hard``)."""
    from bench.torch_dense import vnc_soft_dense

    V, E = mesh.num_vertices, mesh.topology.num_interior
    lim = b.limits
    names = [("vnc_soft_fwd", "torch"), ("vnc_soft_fwd+bwd", "torch.autograd"), ("vnc_hard_fwd+bwd", "torch.autograd")]
    if torch_dev is None:
        if full:
            b.run(Row(name="torch_dense_eq3", variant="pytorch", **common), None, skip=torch_why)
        for name, variant in names:
            b.run(Row(name=name, variant=variant, **common), None, skip=torch_why)
        return
    import torch

    from vnc_warp.torch import vnc_hard as vnc_hard_torch
    from vnc_warp.torch import vnc_soft as vnc_soft_torch

    verts = torch.tensor(mesh.vertices, dtype=torch.float32, device=torch_dev)
    interior = torch.tensor(mesh.topology.interior, dtype=torch.int64, device=torch_dev)
    tau_t = torch.full((V,), float(tau), dtype=torch.float32, device=torch_dev)
    result = {}

    def dense():
        result["H"] = vnc_soft_dense(verts, interior, tau_t)[0]

    def agreement():
        H = vw.vnc_soft(mesh, tau, device=b.device)[0].numpy()
        Ht = result["H"].cpu().numpy()
        out = {"max_abs_dH": float(np.abs(H - Ht).max()), "H_std": float(H.std())}
        if torch_dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats(torch_dev)
            dense()
            out["torch_peak_MB"] = torch.cuda.max_memory_allocated(torch_dev) / 2**20
        return out

    if full:
        b.run(Row(name="torch_dense_eq3", variant="pytorch", note="paper's dense matmul form, blocked", **common),
              dense, skip=None if V * E <= lim["torch"] else f"{V * E:.2g} pairs", reference=ref, check=agreement)
    v = verts.clone().requires_grad_(True)

    def fwd():
        with torch.no_grad():
            vnc_soft_torch(verts, mesh, float(tau))

    def fwd_bwd(op):
        H, n = op(v, mesh, float(tau))
        (H.sum() + n[:, 2].sum()).backward()
        v.grad = None

    pairs = pairs_in_reach(V, E, mesh.area(), tau)
    skip = None if pairs <= lim["grad"] else f"~{pairs:.2g} pairs in reach"
    b.run(Row(name="vnc_soft_fwd", variant="torch", **common), fwd, skip=skip, reference=ref)
    b.run(Row(name="vnc_soft_fwd+bwd", variant="torch.autograd", **common), lambda: fwd_bwd(vnc_soft_torch),
          skip=skip, reference=ref)
    b.run(Row(name="vnc_hard_fwd+bwd", variant="torch.autograd", **common), lambda: fwd_bwd(vnc_hard_torch),
          skip=skip, reference=hard)


def scale_section(b: Bench, mesh: vw.Mesh, info: dict, full: bool) -> None:
    """A whole VNC-Scale curve (16 scales) with VNC-AUC and adaptive scales, against 16 separate calls."""
    dev, lim = b.device, b.limits
    V, E = info["vertices"], info["interior_edges"]
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=dev)
    taus = vw.default_scales(mesh, 16)
    pairs = pairs_in_reach(V, E, info["area"], taus[-1])
    common = dict(section="scale", mesh=mesh.name, tau_label="16 scales", tau=float(taus[-1]))
    phi = {}

    def prepare():
        curve = vw.scale_curve(mesh, taus, device=dev)
        phi["value"] = 0.5 * float(vw.vnc_auc(curve).numpy().mean())

    def curve(strategy="auto"):
        c = vw.scale_curve(mesh, taus, device=dev, strategy=strategy)
        vw.vnc_auc(c)
        vw.adaptive_scale(c, taus, phi["value"])

    skip = None if pairs <= lim["multi"] else f"~{pairs:.2g} pairs within the largest scale"
    if skip is None:
        _safe(prepare)
    if skip is None and "value" not in phi:
        skip = "scale curve failed in preparation"
    ref = b.run(Row(name="scale_curve+auc+adaptive", variant="auto", **common), curve, skip=skip,
                check=lambda: {"chosen": vw.choose_strategy(mesh, float(taus[-1]), device=dev),
                               **(gpu_profile(curve, dev) if not b.args.quick else {})})
    for strategy in ("grid", "dense", "bvh") if full else ():
        work = V * E if strategy == "dense" else pairs
        b.run(Row(name="scale_curve+auc+adaptive", variant=strategy, **common), lambda s=strategy: curve(s),
              skip=skip or (None if work <= lim["bvh" if strategy == "bvh" else "dense"] else f"~{work:.2g} pairs"),
              reference=ref, repeats=1 if strategy == "bvh" else None)
    if full:
        b.run(Row(name="16 x vnc_soft", variant="auto", note="one call per scale", **common),
              lambda: [vw.vnc_soft(mesh, float(t), device=dev) for t in taus], skip=skip, reference=ref)
    b.run(Row(name="scale_curve (hard)", variant="auto", **common),
          lambda: vw.scale_curve(mesh, taus, "hard", device=dev), skip=skip, reference=ref)
    b.run(Row(name="total_complexity", variant="auto", note="what VNC-Flow evaluates per iteration", **common),
          lambda: vflow.total_complexity(mesh, taus, positions=x), skip=skip, reference=ref)


def eq1_section(b: Bench, mesh: vw.Mesh, info: dict) -> None:
    """Eq. (1) on the CPU: trimesh's discrete_mean_curvature_measure against integrated_mean_curvature on the
    same points and radius (and the whole mesh on the benchmark device)."""
    tm = mesh.to_trimesh()
    count = mesh.num_vertices if mesh.num_vertices <= 12_000 else 2000
    count = min(count, 300) if b.args.quick else count
    pts = mesh.vertices[np.linspace(0, mesh.num_vertices - 1, count).astype(np.int64)].astype(np.float64)
    trimesh.curvature.discrete_mean_curvature_measure(tm, pts[:1], info["mean_edge_length"])  # builds its caches
    cpu = get_device("cpu")
    for k in (2.0, 5.0, 10.0):
        r = k * info["mean_edge_length"]
        common = dict(section="eq1", mesh=mesh.name, tau_label=f"r={k:g} l", tau=r)
        out = {}

        def ours():
            out["ours"] = vw.integrated_mean_curvature(mesh, r, pts, device=cpu).numpy()

        def theirs():
            out["trimesh"] = trimesh.curvature.discrete_mean_curvature_measure(tm, pts, r)

        def agree():
            ref = out["trimesh"]
            rel = np.abs(out["ours"] - ref).max() / max(np.abs(ref).max(), 1e-30)
            return {"points": count, "max_rel_diff": float(rel)}

        # warmed as trimesh is (its caches built at another radius): the pieces of the edges that this package
        # keeps with a mesh on the CPU do not depend on the radius either (vnc_warp.tuning.Tuning.cpu_pieces)
        vw.integrated_mean_curvature(mesh, 1.01 * r, pts[:1], device=cpu)
        ref = b.run(Row(name="integrated_mean_curvature", variant="warp-cpu",
                        note=f"{count} points, warmed at r x 1.01", **common), ours, warmup=False)
        b.run(Row(name="trimesh_eq1", variant="numpy+rtree", note=f"{count} points, CPU", **common), theirs,
              reference=ref, check=agree, repeats=1 if b.device.is_cuda else 2, warmup=False)
        if b.device.is_cuda:
            b.run(Row(name="integrated_mean_curvature", variant="device", note="all vertices", **common),
                  lambda: vw.integrated_mean_curvature(mesh, r, device=b.device))


def flow_section(b: Bench, mesh: vw.Mesh, info: dict) -> None:
    """One iteration of Eq. (5) at adaptive scales (VNC-soft + mean + step), as VNC-Flow runs it."""
    dev = b.device
    taus = vw.default_scales(mesh, 16)
    common = dict(section="flow", mesh=mesh.name, tau_label="adaptive")
    pairs = pairs_in_reach(info["vertices"], info["interior_edges"], info["area"], taus[-1])
    if pairs > b.limits["multi"]:
        b.run(Row(name="flow_step", variant="auto", **common), None, skip=f"~{pairs:.2g} pairs at tau_max")
        return
    state = {}

    def prepare():
        curve = vw.scale_curve(mesh, taus, device=dev)
        s = vw.vnc_auc(curve).numpy()
        state["tau"] = vw.adaptive_scale(curve, taus, 0.5 * float(s.mean()))
        state["x"] = wp.array(mesh.vertices, dtype=wp.vec3, device=dev)

    _safe(prepare)
    if "tau" not in state:
        b.run(Row(name="flow_step", variant="auto", **common), None, skip="adaptive scales failed")
        return
    lam, move = 0.1 * info["mean_edge_length"], 0.25 * info["mean_edge_length"]
    b.run(Row(name="flow_step", variant="auto", note="Eq. (5), one iteration", **common),
          lambda: vflow.flow_steps(mesh, state["x"], state["tau"], 1, lam=lam, max_move=move))


def trajectory_section(b: Bench) -> threading.Thread | None:
    """A whole VNC-Flow trajectory, remeshing included, in a worker thread bounded by the time left; returns the
    worker (still alive if it ran out of time)."""
    if b.args.quick:
        src = vw.random_shape(0, subdivisions=3)
        stages, faces, label = 2, None, "random_shape(subdivisions=3), 2 stages"
    else:
        src = load_size(b.args.trajectory_mesh, b.args.meshes, True)
        stages, faces, label = b.args.stages, b.args.trajectory_faces, f"{src.name}, {b.args.stages} stages"
    row = Row(section="trajectory", mesh=src.name, name="vnc_flow_trajectory", variant="auto",
              tau_label="adaptive", note=label)
    b.rows.append(row)
    budget = b.time_left()
    if budget < 10.0:
        row.status, row.note = "skipped", "time budget (--max-minutes) used up"
        return None
    out_dir = tempfile.mkdtemp(prefix="vnc_bench_flow_")
    result = {}

    def work():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.perf_counter()
                traj = vflow.flow(src, stages=stages, faces=faces, device=b.device, out_dir=out_dir, progress=False)
                _synchronize(b.device)
                result["seconds"] = time.perf_counter() - t0
                result["traj"] = traj
        except Exception as exc:
            result["error"] = f"{type(exc).__name__}: {exc}"[:300]

    t0 = time.perf_counter()
    worker = threading.Thread(target=work, daemon=True)
    worker.start()
    worker.join(budget)
    manifest = _read_manifest(out_dir)
    done = max(len(manifest.get("stages", [])) - 1, 0)
    row.extra.update(stages_done=done, stages=stages, out_dir=out_dir)
    if "traj" in result:
        traj = result["traj"]
        row.median_ms = row.min_ms = row.max_ms = result["seconds"] * 1e3
        row.repeats = 1
        row.extra.update(
            faces=int(traj.meshes[-1].num_faces), t_final=float(traj.t[-1]),
            sphericity_final=float(traj.records[-1].get("sphericity", float("nan"))),
            iterations=int(sum(r.get("iterations", 0) for r in traj.records)),
            stage_status={s: sum(r.get("status") == s for r in traj.records)
                          for s in {r.get("status") for r in traj.records}},
            remesh_and_stage_seconds=[round(r.get("seconds", 0.0), 2) for r in traj.records],
        )
    elif "error" in result:
        row.status, row.note = "error", result["error"]
    else:
        row.status = "timeout"
        row.note = f"not finished after {time.perf_counter() - t0:.0f} s ({done}/{stages} stages done)"
    b._print(row)
    return worker


def _read_manifest(out_dir: str) -> dict:
    try:
        with open(os.path.join(out_dir, "manifest.json")) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return {}


def _safe(fn):
    try:
        return fn()
    except Exception:
        return None


# --- goals, output ----------------------------------------------------------------------------------------------------


def _ok(rows, **match) -> list[Row]:
    return [r for r in rows if r.status == "ok" and all(getattr(r, k) == v for k, v in match.items())]


def goals(b: Bench) -> list[dict]:
    """The issue's targets, evaluated on the rows of this run (None: not measured in this run)."""
    rows = b.rows
    big = [name for name, m in b.meshes.items() if 40_000 <= m["vertices"] <= 60_000]
    out = []

    def add(goal, target, value, unit, met, detail=""):
        if b.args.quick:  # sizes and repeats of the smoke run say nothing about the targets
            met, detail = None, "not evaluated in --quick mode"
        out.append({"goal": goal, "target": target, "measured": value, "unit": unit, "met": met, "detail": detail})

    soft = [r for r in _ok(rows, section="operator", name="vnc_soft", variant="auto") if r.mesh in big]
    small = [r for r in soft if r.tau_label in ("2 l", "4 l", "8 l")]
    worst = max(small, key=lambda r: r.median_ms, default=None)
    add("VNC-soft, V~50k, tau <= 8 mean edge lengths", "<= 1 ms", worst and worst.median_ms, "ms",
        None if worst is None else worst.median_ms <= 1.0, worst and f"{worst.mesh} at {worst.tau_label}")
    worst = max(soft, key=lambda r: r.median_ms, default=None)
    add("VNC-soft, V~50k, every tau up to diag/2", "<= 5 ms", worst and worst.median_ms, "ms",
        None if worst is None else worst.median_ms <= 5.0, worst and f"{worst.mesh} at {worst.tau_label}")
    hard = [r for r in _ok(rows, section="operator", name="vnc_hard", variant="auto") if r.mesh in big and r.ratio]
    worst = max(hard, key=lambda r: r.ratio, default=None)
    add("VNC-hard within 2x of VNC-soft at the same tau, V~50k", "<= 2x", worst and worst.ratio, "x soft",
        None if worst is None else worst.ratio <= 2.0, worst and f"{worst.mesh} at {worst.tau_label}")
    curve = [r for r in _ok(rows, section="scale", name="scale_curve+auc+adaptive", variant="auto") if r.mesh in big]
    worst = max(curve, key=lambda r: r.median_ms, default=None)
    add("Scale curve (16 scales) + VNC-AUC + adaptive scales, V~50k", "<= 20 ms", worst and worst.median_ms, "ms",
        None if worst is None else worst.median_ms <= 20.0, worst and worst.mesh)
    traj = _ok(rows, section="trajectory")
    tr = traj[0] if traj else None
    is_goal_run = tr is not None and tr.extra.get("stages") == 32 and not b.args.quick
    add("32-stage VNC-Flow trajectory of a 50k-face mesh, remeshing included", "<= 60 s",
        tr and tr.median_ms / 1e3, "s", (tr.median_ms <= 60e3) if (tr and is_goal_run) else None, tr and tr.note)
    eq1 = [r for r in _ok(rows, section="eq1", name="trimesh_eq1") if r.ratio]
    worst = min(eq1, key=lambda r: r.ratio, default=None)
    add("CPU: integrated_mean_curvature vs trimesh (same mesh, points, radius)", ">= 10x",
        worst and worst.ratio, "x (trimesh / ours)", None if worst is None else worst.ratio >= 10.0,
        worst and f"smallest ratio: {worst.mesh} {worst.tau_label}")
    mem = [r for r in soft if "bytes_per_V+E" in r.extra]
    worst = max(mem, key=lambda r: r.extra["bytes_per_V+E"], default=None)
    add("Memory O(V + E): peak Warp allocation of VNC-soft per (V + E)", "bounded, no V x E buffer",
        worst and worst.extra["bytes_per_V+E"], "bytes", None, worst and f"{worst.mesh} at {worst.tau_label}")
    # issue 22
    compared = [r for r in rows if r.status == "ok" and "vs_baseline" in r.extra]
    slower = sorted((r for r in compared if r.extra["vs_baseline"] > SLOWER), key=lambda r: -r.extra["vs_baseline"])
    add("Every row of the baseline run within 3 % or faster", f"<= {SLOWER}x baseline",
        len(slower) if compared else None, f"rows slower (of {len(compared)} compared)",
        None if not compared else not slower,
        "; ".join(f"{r.mesh} {r.tau_label} {r.key} {r.extra['vs_baseline']:.3f}x" for r in slower[:12])
        or b.baseline_note)
    for goal, target, name, variant, limit in (
            ("VNC-soft at positions= (a flow step) vs the mesh's own vertices, every mesh and scale", "<= 1.5x",
             "vnc_soft", "positions", 1.5),
            ("torch op VNC-soft forward + backward vs the Warp forward, every mesh and scale", "<= 3x",
             "vnc_soft_fwd+bwd", "torch.autograd", 3.0),
            ("VNC-hard vs VNC-soft, every mesh and scale", "<= 2x", "vnc_hard", "auto", 2.0)):
        rs = [r for r in _ok(rows, section="operator", name=name, variant=variant) if r.ratio]
        worst = max(rs, key=lambda r: r.ratio, default=None)
        add(goal, target, worst and worst.ratio, "x", None if worst is None else worst.ratio <= limit,
            worst and f"worst: {worst.mesh} at {worst.tau_label}; over the limit: " + (", ".join(
                f"{r.mesh} {r.tau_label} {r.ratio:.2f}x" for r in rs if r.ratio > limit) or "none"))
    return out


def versions() -> dict:
    import torch

    v = {"python": platform.python_version(), "vnc_warp": vw.__version__, "warp": wp.__version__,
         "torch": torch.__version__, "trimesh": trimesh.__version__, "numpy": np.__version__}
    if torch.cuda.is_available():
        v["torch_cuda"] = torch.version.cuda
    return v


def device_info(dev: wp.Device) -> dict:
    info = {"name": dev.name, "alias": dev.alias, "kind": "cuda" if dev.is_cuda else "cpu",
            "host_cpu": platform.processor() or platform.machine(), "host_cores": os.cpu_count()}
    if dev.is_cuda:
        info.update(sm_count=dev.sm_count, arch=dev.arch, memory_GiB=dev.total_memory / 2**30)
    return info


def write_outputs(b: Bench, command: str) -> dict:
    compare_baseline(b)
    doc = {
        "schema": "vnc-warp-bench/1",
        "command": command,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "device": device_info(b.device),
        "versions": versions(),
        "settings": {"sections": list(b.args.sections), "sizes": list(b.args.sizes), "quick": b.args.quick,
                     "max_minutes": b.args.max_minutes, "target_seconds_per_row": b.target_s,
                     "max_repeats": b.max_repeats, "baseline": b.baseline_note},
        "legend": {
            "timing": "median over repeats after one warm-up call (on a GPU the run's first timed row is called "
                      "untimed for 1 s before, so the clocks leave idle); every call bracketed by device "
                      "synchronisation; inputs (vertex positions) resident on the device",
            "iqr_pct": "interquartile range of the repeats, percent of the median",
            "ratio": "median of this row / median of row ratio_to on the same mesh and scale (> 1: the package is "
                     "faster by that factor)",
            "tau": "scale in mesh units; l = mean edge length, diag = bounding-box diagonal",
            "variant": "traversal strategy of vnc_warp (auto picks grid or dense per call; 'chosen' says which) or "
                       "the baseline's implementation",
            "pairs_in_reach": "expected vertex-edge pairs within the cut-off, sum_k min(E, E pi tau^2 / area)",
            "baseline_ms": "median of the same row in the baseline run (settings.baseline)",
            "vs_baseline": "median / baseline_ms: above 1.03 the row got slower",
        },
        "meshes": list(b.meshes.values()),
        "rows": [asdict(r) for r in b.rows],
        "goals": goals(b),
        "elapsed_s": time.perf_counter() - b.start,
    }
    out = Path(b.args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=_json_default))
    os.replace(tmp, out)
    out.with_suffix(".md").write_text(markdown(doc))
    return doc


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def markdown(doc: dict) -> str:
    """The tables of a run as Markdown (for the README)."""
    d = doc["device"]
    lines = [f"Benchmark of {doc['date'][:10]} on {d['name']} ({d['kind']}); command: `{doc['command']}`.", "",
             "| goal | target | measured | met |", "|---|---|---|---|"]
    for g in doc["goals"]:
        m = "-" if g["measured"] is None else f"{g['measured']:.3g} {g['unit']}"
        met = {True: "yes", False: "**no**", None: "-"}[g["met"]]
        lines.append(f"| {g['goal']} | {g['target']} | {m} | {met} |")
    lines += ["", f"Baseline: {doc['settings'].get('baseline')}.", "",
              "| mesh | V | scale | row | variant | median ms | IQR | vs package | baseline ms | vs baseline | notes |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    verts = {m["name"]: m["vertices"] for m in doc["meshes"]}
    for r in doc["rows"]:
        t = "-" if r["median_ms"] is None else f"{r['median_ms']:.3f}"
        iqr = "" if r["iqr_pct"] is None else f"{r['iqr_pct']:.0f}%"
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}x"
        note = r["note"] if r["status"] == "ok" else f"{r['status']}: {r['note']}"
        extra = ", ".join(f"{k}={_short(v)}" for k, v in r["extra"].items()
                          if k in ("chosen", "max_abs_dH", "max_rel_diff", "stages_done", "t_final", "peak_MB"))
        base = r["extra"].get("baseline_ms")
        vs = r["extra"].get("vs_baseline")
        base = "" if base is None else f"{base:.3f}"
        vs = "" if vs is None else f"{vs:.3f}" + (" **slower**" if vs > SLOWER else "")
        lines.append(f"| {r['mesh']} | {verts.get(r['mesh'], '')} | {r['tau_label']} | {r['name']} | {r['variant']} | "
                     f"{t} | {iqr} | {ratio} | {base} | {vs} | {'; '.join(s for s in (note, extra) if s)} |")
    return "\n".join(lines) + "\n"


def print_tables(doc: dict) -> None:
    print(f"\n{doc['device']['name']} ({doc['device']['kind']}), {doc['date']}, {doc['elapsed_s']:.0f} s")
    print(doc["settings"].get("baseline", ""))
    print(f"{'mesh':14s} {'scale':7s} {'row':26s} {'variant':13s} {'median ms':>10s} {'IQR':>6s} {'vs pkg':>9s} "
          f"{'before ms':>10s} {'vs before':>13s}")
    section = None
    for r in doc["rows"]:
        if r["section"] != section:
            section = r["section"]
            print(f"-- {section}")
        print(_format_row(Row(**{k: v for k, v in r.items()})))
    print("\ngoals:")
    for g in doc["goals"]:
        m = "not measured" if g["measured"] is None else f"{g['measured']:.3g} {g['unit']}"
        met = {True: "MET", False: "NOT MET", None: "-"}[g["met"]]
        print(f"  [{met:7s}] {g['goal']}: target {g['target']}, measured {m} {g['detail'] or ''}")


# --- entry point ------------------------------------------------------------------------------------------------------


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m bench.vnc", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: Warp's preferred device")
    p.add_argument("--out", default="bench/results/bench.json",
                   help="JSON output (a .md copy of the tables beside it); a path not ending in .json is a folder, "
                        "which gets bench.json and bench.md")
    p.add_argument("--quick", action="store_true", help="a small smoke run: 3k-vertex Spot, three scales, tiny flow")
    p.add_argument("--sizes", default=None,
                   help=f"comma-separated sizes from {', '.join(SIZES)}; default: 50k,50k-koala,10k,200k,800k,15k,"
                        f"30k-hammer on CUDA, 10k on the CPU, 3k with --quick; every strategy and the PyTorch baseline run on "
                        f"{', '.join(FULL_SIZES)}")
    p.add_argument("--sections", default=None,
                   help=f"comma-separated sections from {', '.join(SECTIONS)}; default: all (on the CPU without "
                        "--quick: all but the trajectory)")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="wall-clock budget; rows past it are reported as skipped (default 6 on CUDA, 30 on the CPU, "
                        "1 with --quick)")
    p.add_argument("--meshes", type=Path, default=MESH_DIR,
                   help="folder of the real meshes (nefertiti.obj, koala.obj, spot.obj, armadillo.obj, hammer.obj)")
    p.add_argument("--trajectory-mesh", default="50k-koala", help="size whose mesh the trajectory starts from")
    p.add_argument("--trajectory-faces", type=int, default=50_000, help="face count of the remeshed flow states")
    p.add_argument("--stages", type=int, default=32, help="stages of the trajectory")
    p.add_argument("--verbose", action="store_true", help="print every row as it is measured")
    p.add_argument("--baseline", default=str(BASELINE) if BASELINE.exists() else None,
                   help="JSON of an earlier run whose rows each row is set beside (compared when it ran on a device "
                        "of the same name); '' for none")
    args = p.parse_args(argv)
    if not args.out.endswith(".json"):
        args.out = str(Path(args.out) / "bench.json")
    device = get_device(args.device)
    if args.sizes is None:
        args.sizes = "3k" if args.quick else ("50k,50k-koala,10k,200k,800k,15k,30k-hammer" if device.is_cuda
                                              else "10k")
    args.sizes = [s for s in args.sizes.split(",") if s]
    if args.sections is None:
        args.sections = ",".join(s for s in SECTIONS if device.is_cuda or args.quick or s != "trajectory")
    args.sections = [s for s in args.sections.split(",") if s]
    for s in args.sections:
        if s not in SECTIONS:
            p.error(f"unknown section {s!r}; choose from {', '.join(SECTIONS)}")
    if args.max_minutes is None:
        args.max_minutes = 1.0 if args.quick else (6.0 if device.is_cuda else 30.0)
    return args


def main(argv=None) -> tuple[dict, threading.Thread | None]:
    """Run the benchmark; returns the JSON document and the trajectory worker (alive if it ran out of time)."""
    args = parse_args(argv)
    command = "python -m bench.vnc " + " ".join(sys.argv[1:] if argv is None else argv)
    with wp.ScopedDevice(args.device):
        b = Bench(args)
        taus = QUICK_TAUS if args.quick else TAUS
        for size in args.sizes:  # load lazily: the large subdivided meshes only if time is left for them
            if b.time_left(b.reserve) <= 0:
                b.rows.append(Row(section="meshes", mesh=size, name="load", variant="-", status="skipped",
                                  note="time budget (--max-minutes) used up"))
                continue
            try:
                mesh = load_size(size, args.meshes, b.device.is_cuda)
            except Exception as exc:
                b.rows.append(Row(section="meshes", mesh=size, name="load", variant="-", status="error",
                                  note=f"{type(exc).__name__}: {exc}"[:300]))
                continue
            info = b.meshes[mesh.name] = mesh_info(mesh, size)
            full = size in FULL_SIZES
            if "operator" in args.sections:
                operator_section(b, mesh, info, taus, full)
            if "scale" in args.sections:
                scale_section(b, mesh, info, full)
            if "eq1" in args.sections and size in EQ1_SIZES:
                eq1_section(b, mesh, info)
            if "flow" in args.sections:
                flow_section(b, mesh, info)
            write_outputs(b, command)
        worker = trajectory_section(b) if "trajectory" in args.sections else None
        doc = write_outputs(b, command)
    print_tables(doc)
    print(f"\nwrote {args.out} and {Path(args.out).with_suffix('.md')}", flush=True)
    return doc, worker


if __name__ == "__main__":
    _, _worker = main()
    if _worker is not None and _worker.is_alive():
        # a trajectory past its time budget still runs in Warp's native code: leave without interpreter teardown
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
