"""VNC-Flow (paper Sec. 3.2, Algorithm 1): spacetime-balanced curvature flow sampling.

A detailed mesh goes in; a :class:`Trajectory` of ``stages + 1`` meshes and their normalized times
``t`` (Eq. 7) comes out, from the remeshed input (``t = 1``) to a near-sphere.

* **Flow step**, Eq. (5): ``v_k <- v_k - lambda (H_soft(v_k, tau_k) - H_ref) n_soft(v_k, tau_k)`` with
  ``H_ref`` the vertex mean of ``H_soft`` at the current iterate (the scale-stable global reference: the
  mean barely depends on scale, Fig. 6, and taking it at the current state keeps the flow from drifting
  inward or outward), added in a fixed order (:func:`reference_mean`) so that a run repeats bit for bit.
* **Step size rule**: at the first iteration of each stage ``lambda = eta * mean_edge_length / q90(|H - H_ref|)``
  (the 90th-percentile vertex moves ``eta`` mean edge lengths), capped at ``max_lambda`` mean edge lengths for
  stability, then held for the stage so moves shrink as the surface converges; every move is clamped to
  ``eta`` times the vertex's own mean incident edge length. The rule is unit-free.
* **Spatial balance**, Eq. (6): per-vertex adaptive scales ``tau_k`` from the stage's VNC-Scale curves
  with ``phi = phi_fraction * mean_k s(v_k)``; recomputed at the start of every stage.
* **Temporal balance**: ``S_init = sum_k s(v_k | M0)``, ``phi_stage = S_init / N``; stage ``i`` iterates
  until ``S_init - S_cur >= i * phi_stage`` and records ``t_i = S_cur / S_init`` (Eq. 7). A stage that
  stops improving (no 0.1 % gain in ``patience`` evaluations) or reaches ``max_iters`` ends with a warning and
  records the ``t`` it actually reached: a meshed sphere's VNC-AUC is not exactly zero.
* **Topology regularization**: :func:`vnc_warp.remesh.sdf_remesh` before stage 0 and between stages.

The scale range is fixed from ``M0`` for the whole trajectory so every ``S`` is measured the same way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import flow as _k

from ._device import get_device
from .mesh import Mesh, MeshError, from_arrays, load_mesh
from .operators import vnc_soft
from .scale import adaptive_scale, default_scales, scale_curve, vnc_auc
from .trajectory import Trajectory, resume

__all__ = ["FlowParams", "Trajectory", "FlowError", "flow", "flow_steps", "reference_mean", "total_complexity",
           "sphericity"]


class FlowError(RuntimeError):
    """VNC-Flow produced an invalid state (a bug, never recorded) or cannot resume."""


@dataclass
class FlowParams:
    """Parameters of :func:`flow` (all unit-free; scales come from the mesh).

    Attributes:
        stages: number of stages N of Algorithm 1.
        faces: face count of every remeshed state; None keeps the input's.
        num_scales: scales of the VNC-Scale curves (geometric, :func:`vnc_warp.default_scales`).
        kappa: VNC-soft cut-off ratio.
        step_fraction: eta of the step size rule (fraction of the mean edge length per iteration).
        max_lambda: stability cap on lambda, in mean edge lengths per radian of curvature deviation. The
            explicit step diverges above about 12-16 (measured on Spot with the default scales); 6 keeps a
            factor of two.
        phi_fraction: Eq. (6) budget as a fraction of the stage's mean per-vertex VNC-AUC.
        max_iters: iteration cap per stage.
        eval_every: evaluate ``S_cur`` at least this many iterations apart.
        eval_max: at most this many iterations apart. In between, the next evaluation is placed about halfway
            to the stage's budget at the decay rate observed so far (the 16-scale evaluation of ``S`` costs
            several flow steps).
        patience: evaluations without a 0.1 % decrease of ``S_cur`` before a stage counts as converged.
        remesh: SDF-remesh before stage 0 and between stages.
        resolution: marching-cubes grid resolution of the remesher (None: automatic).
        scale_mode: "adaptive" (Eq. 6), "small" (every vertex at tau_min) or "large" (tau_max): Fig. 7 (c, d).
        method: "vnc" (Eq. 5), "mcf_explicit" or "mcf_implicit" (cotangent-Laplacian mean curvature flow,
            Fig. 7 (e, f)); the baselines use the same stages and records, with ``mcf_dt`` in units of the
            squared mean edge length.
        mcf_dt: time step of the MCF baselines (None: 0.05 explicit, inside its stability limit of about 1/6,
            and 5.0 implicit).
    """

    stages: int = 32
    faces: int | None = None
    num_scales: int = 16
    kappa: float = 6.0
    step_fraction: float = 0.25
    max_lambda: float = 6.0
    phi_fraction: float = 0.5
    max_iters: int = 300
    eval_every: int = 1
    eval_max: int = 8
    patience: int = 15
    remesh: bool = True
    resolution: int | None = None
    scale_mode: str = "adaptive"
    method: str = "vnc"
    mcf_dt: float | None = None

    def __post_init__(self):
        if self.stages < 1:
            raise ValueError(f"stages must be >= 1, got {self.stages}")
        if self.scale_mode not in ("adaptive", "small", "large"):
            raise ValueError(f"scale_mode must be adaptive, small or large, got {self.scale_mode!r}")
        if self.method not in ("vnc", "mcf_explicit", "mcf_implicit"):
            raise ValueError(f"method must be vnc, mcf_explicit or mcf_implicit, got {self.method!r}")
        for name in ("step_fraction", "phi_fraction", "kappa"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.max_iters < 1 or self.eval_every < 1 or self.patience < 1 or self.eval_max < self.eval_every:
            raise ValueError("max_iters, eval_every and patience must be >= 1, and eval_max >= eval_every")


def _euler(mesh: Mesh) -> int:
    """Euler characteristic V - E + F (2 for a sphere, 0 for a torus): remeshing may close a handle."""
    return int(mesh.num_vertices - mesh.topology.edges.shape[0] + mesh.num_faces)


def sphericity(mesh: Mesh) -> float:
    """Isoperimetric quotient ``36 pi V^2 / A^3``: 1 for a sphere, smaller for anything else."""
    return float(36.0 * np.pi * mesh.volume() ** 2 / mesh.area() ** 3)


def total_complexity(mesh: Mesh, taus, *, kappa: float = 6.0, positions: wp.array | None = None, device=None) -> float:
    """``S = sum_k s(v_k)``: the total VNC-AUC (Eq. 4 at tau_max) of a mesh, the numerator of Eq. (7)."""
    curve = scale_curve(mesh, taus, "soft", kappa=kappa, device=device, positions=positions)
    return float(np.sum(vnc_auc(curve).numpy(), dtype=np.float64))


def _mesh_digest(mesh: Mesh) -> str:
    h = hashlib.sha256(np.ascontiguousarray(mesh.vertices).tobytes())
    h.update(np.ascontiguousarray(mesh.faces).tobytes())
    return h.hexdigest()[:16]


def _local_edge_length(mesh: Mesh) -> np.ndarray:
    """(V,) float32 mean length of each vertex's incident edges, in mesh units (float64 sums in edge order on the
    host, so every device clamps the moves of Eq. (5) alike)."""
    e = mesh.topology.edges
    v = mesh.vertices.astype(np.float64)
    length = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)
    V = mesh.num_vertices
    total = np.bincount(e[:, 0], length, V) + np.bincount(e[:, 1], length, V)
    count = np.bincount(e[:, 0], minlength=V) + np.bincount(e[:, 1], minlength=V)
    return (total / np.maximum(count, 1)).astype(np.float32)


def reference_mean(H: wp.array, out: wp.array, *, partial: wp.array | None = None, tape: wp.Tape | None = None) -> None:
    """``out[0] = mean_k H[k]``, the global reference ``H_ref`` of Eq. (5), added in a fixed order.

    Float64 partial sums of a fixed stride (:data:`vnc_warp.kernels.flow.MEAN_PARTS`), then one thread adds them in
    order: unlike an atomic float sum (whose order follows thread timing on CUDA) the result is the same on every
    run and every device that computes the same ``H``, and within rounding of the float64 mean.

    Args:
        H: (V,) float32 values.
        out: (1,) float32, overwritten.
        partial: (MEAN_PARTS,) float64 scratch on ``H``'s device (allocated when None).
        tape: the ``wp.Tape`` being recorded: the adjoint ``H.grad += out.grad / V`` is recorded on it.
    """
    device = H.device
    V = H.shape[0]
    if partial is None:
        partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
    wp.launch(_k.strided_sums, dim=partial.shape[0], inputs=[H], outputs=[partial], device=device, record_tape=False)
    wp.launch(_k.ordered_mean, dim=1, inputs=[partial, wp.float64(1.0 / V)], outputs=[out], device=device,
              record_tape=False)
    if tape is not None:
        def backward():
            wp.launch(_k.mean_adjoint, dim=V, inputs=[out.grad, 1.0 / V], outputs=[H.grad], device=device,
                      record_tape=False)

        tape.record_func(backward=backward, arrays=[H, out])


def flow_steps(
    mesh: Mesh,
    positions: wp.array,
    tau,
    steps: int,
    *,
    lam: float,
    max_move,
    kappa: float = 6.0,
    tape: wp.Tape | None = None,
) -> list:
    """``steps`` iterations of Eq. (5) at fixed adjacency, each writing a new state: differentiable on a tape.

    Args:
        mesh: connectivity (positions come from ``positions``).
        positions: (V,) vec3 initial state; ``requires_grad=True`` to differentiate.
        tau: per-vertex scales (scalar or (V,)), held fixed.
        steps: number of iterations K.
        lam: step size lambda (mesh units, held fixed).
        max_move: per-vertex move clamp (scalar or (V,)).
        kappa: VNC-soft cut-off ratio.
        tape: the ``wp.Tape`` being recorded, if any.

    Returns:
        The K+1 states ``[x_0, ..., x_K]`` (``x_0`` is ``positions``).
    """
    from .operators import _per_point

    device = positions.device
    V = mesh.num_vertices
    tau_arr = _per_point(tau, V, device, "tau")
    mm = _per_point(max_move, V, device, "max_move")
    partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
    states = [positions]
    for _ in range(steps):
        x = states[-1]
        H, n = vnc_soft(mesh, tau_arr, kappa=kappa, positions=x, tape=tape)
        ref = wp.zeros(1, dtype=wp.float32, device=device, requires_grad=x.requires_grad)
        reference_mean(H, ref, partial=partial, tape=tape)
        out = wp.empty(V, dtype=wp.vec3, device=device, requires_grad=x.requires_grad)
        wp.launch(_k.flow_step, dim=V, inputs=[x, H, n, ref, float(lam), mm], outputs=[out], device=device)
        states.append(out)
    return states


class _Stepper:
    """One stage's iteration: Eq. (5) (VNC) or a cotangent-Laplacian MCF baseline."""

    def __init__(self, mesh: Mesh, taus: np.ndarray, p: FlowParams, device):
        self.mesh, self.p, self.device = mesh, p, device
        V = mesh.num_vertices
        self.x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
        self.x_next = wp.empty_like(self.x)
        self.ref = wp.zeros(1, dtype=wp.float32, device=device)
        self.partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
        self.edge = mesh.mean_edge_length
        self.lam = None
        if p.method == "vnc":
            curve = scale_curve(mesh, taus, "soft", kappa=p.kappa, device=device)
            if p.scale_mode == "adaptive":
                s = vnc_auc(curve).numpy()
                self.tau = adaptive_scale(curve, taus, p.phi_fraction * float(s.mean()))
            else:
                t = taus[0] if p.scale_mode == "small" else taus[-1]
                self.tau = wp.array(np.full(V, t, dtype=np.float32), device=device)
            self.max_move = wp.array(p.step_fraction * _local_edge_length(mesh), dtype=wp.float32, device=device)
        else:
            self._laplacian()

    def _laplacian(self):
        import scipy.sparse as sp

        v = self.mesh.vertices.astype(np.float64)
        f = self.mesh.faces
        V = v.shape[0]
        rows, cols, vals = [], [], []
        area = np.zeros(V)
        for i in range(3):
            a, b, c = f[:, i], f[:, (i + 1) % 3], f[:, (i + 2) % 3]
            u, w = v[b] - v[a], v[c] - v[a]
            cot = (u * w).sum(1) / np.maximum(np.linalg.norm(np.cross(u, w), axis=1), 1e-30)
            rows += [b, c]
            cols += [c, b]
            vals += [0.5 * cot, 0.5 * cot]
        tri = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        for i in range(3):
            np.add.at(area, f[:, i], tri / 3.0)
        W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(V, V)).tocsr()
        self.L = W - sp.diags(np.asarray(W.sum(1)).ravel())
        self.M = sp.diags(area)
        default = 0.05 if self.p.method == "mcf_explicit" else 5.0
        self.dt = (self.p.mcf_dt or default) * self.edge**2
        if self.p.method == "mcf_implicit":
            from scipy.sparse.linalg import factorized

            self.solve = factorized((self.M - self.dt * self.L).tocsc())

    def step(self) -> None:
        p = self.p
        if p.method == "vnc":
            H, n = vnc_soft(self.mesh, self.tau, kappa=p.kappa, positions=self.x)
            reference_mean(H, self.ref, partial=self.partial)
            if self.lam is None:
                q = float(np.quantile(np.abs(H.numpy() - self.ref.numpy()[0]), 0.9))
                self.lam = min(p.step_fraction / q if q > 0 else 0.0, p.max_lambda) * self.edge
            V = self.mesh.num_vertices
            wp.launch(_k.flow_step, dim=V, inputs=[self.x, H, n, self.ref, self.lam, self.max_move],
                      outputs=[self.x_next], device=self.device)
            self.x, self.x_next = self.x_next, self.x
            return
        v = self.x.numpy().astype(np.float64)
        if p.method == "mcf_explicit":
            v = v + self.dt * (self.L @ v) / self.M.diagonal()[:, None]
        else:
            v = np.stack([self.solve(self.M @ v[:, d]) for d in range(3)], axis=1)
        self.x = wp.array(v.astype(np.float32), dtype=wp.vec3, device=self.device)

    def current(self) -> Mesh:
        return Mesh(self.x.numpy(), self.mesh.faces, self.mesh.topology, self.mesh.name)


def _as_saved(mesh: Mesh) -> Mesh:
    """The state as a resumed run reads it back: float32 vertices with no float64 history (the stage PLY holds
    float32), so that a run resumed from its files continues bit-identically to one never interrupted."""
    return Mesh(np.ascontiguousarray(mesh.vertices, dtype=np.float32), mesh.faces, mesh.topology, mesh.name)


def _check_state(mesh: Mesh) -> str | None:
    from .remesh import surface_problems

    problems = surface_problems(mesh.vertices, mesh.faces)
    return "; ".join(problems) if problems else None


def _params_key(p: FlowParams) -> dict:
    return dataclasses.asdict(p)


def flow(
    mesh,
    stages: int = 32,
    faces: int | None = None,
    device=None,
    *,
    out_dir: str | os.PathLike | None = None,
    progress: bool = True,
    **params,
) -> Trajectory:
    """Run VNC-Flow (Algorithm 1) and return the trajectory; see the module docstring for the rules.

    Args:
        mesh: input mesh: a :class:`Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path;
            it must be watertight unless ``remesh`` is on (the SDF remesher closes holes with the winding-number
            sign).
        stages: number of stages N.
        faces: face count of the remeshed states (None: the input's).
        device: Warp device.
        out_dir: write each stage as soon as it is finished (PLY + ``manifest.json``, :mod:`vnc_warp.trajectory`);
            if the folder already holds a run with the same input and parameters, resume after its last finished
            stage. The folder is checked before anything is computed.
        progress: show a progress bar (stage, iterations, t, seconds).
        **params: any other :class:`FlowParams` field.

    Returns:
        The :class:`Trajectory` (N+1 meshes unless a baseline collapsed first).

    Raises:
        MeshError: the input is not watertight and ``remesh=False``, or is otherwise invalid.
        FlowError: a VNC-Flow state failed validity (a bug).
        TrajectoryError: ``out_dir`` holds a different run, stage files it does not own, or damaged files.
        OSError: ``out_dir`` cannot be created or written to.
    """
    from .remesh import sdf_remesh

    p = FlowParams(stages=stages, faces=faces, **params)
    device = get_device(device)
    src = load_mesh(mesh)
    if not p.remesh and not src.is_watertight:
        raise MeshError(f"{src.name}: not watertight ({src.topology.boundary.shape[0]} boundary edges); "
                        "VNC-Flow needs a closed surface: enable remesh (SDF remeshing closes it)")
    info = {"params": _params_key(p), "source": src.name, "source_digest": _mesh_digest(src),
            "version": _version(), "device": str(device)}
    traj = resume(out_dir, info) if out_dir is not None else None
    t_start = time.perf_counter()
    if traj is None:
        m0 = _as_saved(sdf_remesh(src, faces=p.faces, resolution=p.resolution, device=device) if p.remesh else src)
        taus = default_scales(m0, p.num_scales)
        S_init = total_complexity(m0, taus, kappa=p.kappa, device=device)
        if not S_init > 0:
            raise FlowError(f"{src.name}: total VNC-AUC is {S_init}; nothing to flow")
        info.update(taus=taus.tolist(), S_init=S_init, phi_stage=S_init / p.stages)
        rec = {"index": 0, "t": 1.0, "S": S_init, "file": "stage_000.ply", "iterations": 0,
               "seconds": time.perf_counter() - t_start, "sphericity": sphericity(m0), "vertices": m0.num_vertices,
               "faces": m0.num_faces, "euler": _euler(m0), "status": "input"}
        traj = Trajectory([m0], np.array([1.0]), [rec], info)
        if out_dir is not None:
            traj.save(out_dir)
    taus = np.asarray(traj.info["taus"])
    S_init, phi_stage = traj.info["S_init"], traj.info["phi_stage"]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=p.stages, initial=len(traj.meshes) - 1, desc=f"VNC-Flow {src.name}", unit="stage")
    try:
        while len(traj.meshes) <= p.stages and traj.records[-1]["status"] != "collapsed":
            i = len(traj.meshes)
            t0 = time.perf_counter()
            prev = traj.meshes[-1]
            cur = sdf_remesh(prev, faces=p.faces or traj.meshes[0].num_faces, resolution=p.resolution,
                             device=device) if (p.remesh and i > 1) else prev
            rec = _run_stage(cur, i, taus, S_init, phi_stage, p, device, bar)
            state = _as_saved(rec.pop("_mesh"))
            rec.update(file=f"stage_{i:03d}.ply", seconds=time.perf_counter() - t0)
            traj.meshes.append(state)
            traj.records.append(rec)
            traj.t = np.append(traj.t, rec["t"])
            if out_dir is not None:
                traj.save(out_dir)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(it=rec["iterations"], t=f"{rec['t']:.3f}", s=f"{rec['seconds']:.1f}")
    finally:
        if bar is not None:
            bar.close()
    return traj


def _run_stage(mesh: Mesh, i: int, taus, S_init: float, phi_stage: float, p: FlowParams, device, bar) -> dict:
    target = S_init - i * phi_stage
    stepper = _Stepper(mesh, taus, p, device)
    S_cur = ref = best = total_complexity(mesh, taus, kappa=p.kappa, device=device)
    stale, it, status = 0, 0, "budget"
    last_valid, best_x = mesh, None
    history = [[0, S_cur]]
    next_eval = p.eval_every
    while S_cur > target:
        if it >= p.max_iters:
            status = "max_iters"
            break
        stepper.step()
        it += 1
        if it < next_eval:
            continue
        if p.method != "vnc":
            if _check_state(stepper.current()):
                status = "collapsed"
                break
            last_valid = stepper.current()
        S_prev, S_cur = S_cur, total_complexity(mesh, taus, kappa=p.kappa, positions=stepper.x, device=device)
        rate = (S_prev - S_cur) / (it - history[-1][0])
        history.append([it, S_cur])
        # the next evaluation lands about halfway to the budget at the observed decay rate
        ahead = int(0.5 * (S_cur - target) / rate) if rate > 0 else 0
        next_eval = it + max(p.eval_every, min(ahead, p.eval_max))
        if bar is not None:
            bar.set_postfix(stage=i, it=it, t=f"{S_cur / S_init:.3f}")
        if S_cur < best:
            best, best_x = S_cur, wp.clone(stepper.x)
        if S_cur < ref * (1.0 - 1e-3):
            ref, stale = S_cur, 0
        else:
            stale += 1
            if stale >= p.patience:
                status = "converged"
                break
    if status in ("max_iters", "converged") and best_x is not None and best < S_cur:
        stepper.x, S_cur = best_x, best  # a stage that cannot meet its budget keeps its best state
    state = stepper.current()
    if status == "collapsed":
        state = last_valid
        S_cur = total_complexity(state, taus, kappa=p.kappa, device=device)
    problem = _check_state(state)
    if problem:
        raise FlowError(f"VNC-Flow stage {i} produced an invalid surface ({problem}); this is a bug, please report it")
    if status in ("max_iters", "converged"):
        warnings.warn(f"VNC-Flow stage {i}: {status} after {it} iterations at t = {S_cur / S_init:.4f} "
                      f"(budget t = {max(target, 0.0) / S_init:.4f}); recording the t reached", stacklevel=3)
    return {"index": i, "t": S_cur / S_init, "S": S_cur, "target_t": max(target, 0.0) / S_init, "iterations": it,
            "status": status, "sphericity": sphericity(state), "vertices": state.num_vertices,
            "faces": state.num_faces, "euler": _euler(state), "history": history, "_mesh": state}


def _version() -> str:
    from . import __version__

    return __version__
