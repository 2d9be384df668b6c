"""The VNC engine: the state of the operator for one mesh on one device, and every launch sequence of it.

``vw.engine(mesh, device)`` returns the :class:`Engine` of a (mesh, device) pair (and tuning), made on first use and
kept while the mesh lives; every operator of :mod:`vnc_warp.operators`, :mod:`vnc_warp.scale` and :mod:`vnc_warp.torch`
calls through it. It owns what calls on one mesh share: the mesh's vertices and interior edges on the device, the
edge fields and (on the CPU) the sorted pieces of its own edges, the Morton orders of its queries, the scratch buffers,
the captured graphs (:mod:`vnc_warp._replay`) and the plans of positions given on the device.

A flow holds an engine and calls it with the positions of each step::

    engine = vw.engine(mesh, device)
    H, n = engine.vnc_soft(tau, kappa=6.0, positions=x)          # Eq. (3) at device positions x, per-vertex tau
    S = engine.total_complexity(taus, kappa=6.0, positions=x)    # sum of Eq. (4) over the vertices (one read)
    H16, mean = engine.scale_curve(taus, positions=x)            # the (S, V) VNC-Scale curves and their mean

Positions given on the device (a flow step, the torch op) take a *plan*: the grid and launch shape are chosen once from
their bounds (one read from the device, the first time), then reused while only the positions move, so a call reads
nothing back and is replayed from a captured graph from its third time on. The grid stays exact for positions that
leave the box it was made for (:mod:`kernels.vnc_grid`); each call also measures its positions' bounds on the device,
and a later call that finds them drifted past :attr:`Tuning.replan_cells` or :attr:`Tuning.replan_ratio` (or holding
NaN) makes the plan again, reading the bounds then. So invalid positions given on the device raise at a plan's first
call; once a plan exists, at the next call (the call that held them gives NaN where they reach).
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import vnc_grid as _g
from vnc_warp.kernels import vnc_reference as _ref
from vnc_warp.kernels import vnc_scale as _ks
from vnc_warp.kernels import vnc_sums as _s
from vnc_warp.kernels.vnc_terms import edge_geometry

from . import _plan
from ._checks import check_kappa, host_array, host_scalar, per_point, radius_stats
from ._device import get_device
from ._reduce import ordered_sum
from ._replay import Replay, replayed_kinds
from .mesh import Mesh, MeshError
from .tuning import DEFAULT, Tuning

__all__ = ["Engine", "EdgeFields", "engine", "engine_of"]


@dataclass
class EdgeFields:
    """Per-interior-edge quantities on one device (Sec. 3.1).

    Attributes:
        edges: (Ei,) vec4i ``(a, b, c0, c1)``.
        mid: (Ei,) vec3 midpoints.
        length: (Ei,) float32 full edge lengths ``L_j``.
        angle: (Ei,) float32 signed dihedral angles ``alpha_j * delta_j`` (radians).
        normal: (Ei,) vec3 unit area-weighted normals of the two faces.
    """

    edges: wp.array
    mid: wp.array
    length: wp.array
    angle: wp.array
    normal: wp.array


_ENGINES: "weakref.WeakKeyDictionary[Mesh, dict]" = weakref.WeakKeyDictionary()


def engine(mesh: Mesh, device=None, *, tuning: Tuning | None = None) -> "Engine":
    """The :class:`Engine` of ``mesh`` on ``device`` (default: Warp's preferred device) with ``tuning`` (default
    :data:`vnc_warp.tuning.DEFAULT`): made on first use, kept while the mesh lives, made again when the mesh's
    vertex array is replaced (a Mesh's arrays are treated as immutable)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"engine: expected a vw.Mesh, got {type(mesh).__name__}")
    device = get_device(device)
    tuning = DEFAULT if tuning is None else tuning
    if not isinstance(tuning, Tuning):
        raise TypeError(f"tuning must be a vw.Tuning, got {type(tuning).__name__}")
    per_mesh = _ENGINES.setdefault(mesh, {})
    key = (device.alias, tuning)
    found = per_mesh.get(key)
    if found is None or found.vertices is not mesh.vertices:
        found = per_mesh[key] = Engine(mesh, device, tuning)
    return found


def engine_of(src, device=None, positions=None, tuning: Tuning | None = None) -> "Engine":
    """The engine of an operator call on ``src`` (a :class:`~vnc_warp.mesh.MeshInput`): on ``positions``' device,
    else ``device``, else the device of the caller's tensor, else the preferred one."""
    if positions is not None:
        if not isinstance(positions, wp.array):
            raise TypeError("positions must be a wp.array of wp.vec3")
        device = positions.device
    elif device is None:
        device = src.device
    return engine(src.mesh, device, tuning=tuning)


class _Moving:
    """The plan of one kind of call with positions given on the device: its bounds and concrete strategy, the
    engine's copies of the positions (and per-vertex scales) that its graph reads, and the bounds of the last call's
    positions, measured on the device and read back only once they are there (:meth:`poll`)."""

    def __init__(self, engine: "Engine", key: tuple, bounds: _plan.Bounds, strategy: str, tau_array: bool):
        device = engine.device
        V = engine.num_vertices
        self.key, self.bounds, self.strategy = key, bounds, strategy
        self.x = wp.empty(V, dtype=wp.vec3, device=device)
        self.tau = wp.empty(V, dtype=wp.float32, device=device) if tau_array else None
        self.stats = wp.empty(_plan.STATS_SIZE, dtype=wp.float32, device=device)
        self.partial = _plan.stats_partial(device)
        self.preset = _plan.stats_init(device)
        if device.is_cuda:
            self.host = wp.empty(_plan.STATS_SIZE, dtype=wp.float32, device="cpu", pinned=True)
            self.view = self.host.numpy()  # a view of the host memory the bounds are copied into
        else:  # the CPU device has run each launch when it returns: the bounds are read where they are measured
            self.host, self.view = None, self.stats.numpy()
        self.event = wp.Event(device) if device.is_cuda else None
        self.pending = False
        self.prep = None  # what the last forward call prepared (fields, traversal, records, sums) ...
        self.token = None  # ... and the engine's token of that call

    def load(self, x: wp.array | None, tau) -> None:
        """Copy the call's positions (None: the caller wrote them into :attr:`x`) and array of scales into the
        arrays the plan's launches read."""
        if x is not None:
            wp.copy(self.x, x)
        if self.tau is not None:
            if isinstance(tau, wp.array):
                wp.copy(self.tau, per_point(tau, self.tau.shape[0], self.tau.device, "tau"))
            else:
                self.tau.assign(host_array(tau, self.tau.shape[0], "tau"))

    def measure(self, radius: wp.array | None, *, copy_out: bool = False) -> None:
        """Enqueue the bounds of the loaded positions (and scales) into :attr:`stats` (part of the call's graph);
        ``copy_out``: and their copy to the host (a graph's, so that a replay needs no copy of its own)."""
        wp.copy(self.stats, self.preset)
        empty = self.stats[:0]
        _plan.launch_stats(self.x, radius if radius is not None else empty, empty, self.stats, self.partial)
        if copy_out and self.host is not None:
            wp.copy(self.host, self.stats)

    def fetch(self, copied: bool = False) -> None:
        """Start copying the measured bounds to the host (``copied``: the call's launches did), :meth:`poll` reads
        them once they are there."""
        if self.x.device.is_capturing:
            return
        if self.host is not None and not copied:
            wp.copy(self.host, self.stats)
        if self.event is not None:
            wp.record_event(self.event)
        self.pending = True

    def poll(self) -> list[float] | None:
        """The bounds of the last call as Python floats, once they have arrived (never waits), else None."""
        if not self.pending or (self.event is not None and not self.event.is_complete):
            return None
        self.pending = False
        return self.view.tolist()

    def drifted(self, s: list[float], t: Tuning) -> bool:
        """Whether the positions (or scales) measured in ``s`` call for a new plan: invalid values, a box moved more
        than ``t.replan_cells`` cells past the plan's or shrunk, or scales changed by more than ``t.replan_ratio``.
        (Every call tests this: scalar float arithmetic, as NumPy's on 3-vectors would cost more than the rest of a
        replayed call's host time.)"""
        if s[10] > 0 or s[11] > 0:
            return True
        b = self.bounds
        slack = t.replan_cells * t.cell_fraction * max(b.rmean, 1e-30)
        for i, (lo, hi) in enumerate(zip(b.lo.tolist(), b.hi.tolist())):
            if s[i] < lo - slack or s[3 + i] > hi + slack:
                return True
            ext0 = hi - lo
            if ext0 > 0 and (s[3 + i] - s[i]) * t.replan_ratio < ext0:
                return True
        if self.tau is not None:
            rmean = s[7] / max(self.tau.shape[0], 1)
            if not b.rmean / t.replan_ratio <= rmean <= b.rmean * t.replan_ratio:
                return True
        return False


class _Token:
    """The token of a VNC-soft call that leaves what its backward pass reuses: its plan and its arguments as given."""

    __slots__ = ("plan", "tau", "kappa")

    def __init__(self, plan: _Moving, tau, kappa: float):
        self.plan, self.tau, self.kappa = plan, tau, kappa


class Engine:
    """The VNC operator (Sec. 3.1) on one mesh and one device: see the module docstring.

    Args:
        mesh: the checked mesh (its vertices, relative to ``mesh.origin``, and interior edges are copied to the
            device once).
        device: a Warp device.
        tuning: the knobs (:class:`~vnc_warp.tuning.Tuning`).
    """

    def __init__(self, mesh: Mesh, device, tuning: Tuning = DEFAULT):
        self.device = get_device(device)
        self.tuning = tuning
        self.name = mesh.name
        self.vertices = mesh.vertices  # the array this engine was made for
        self.num_vertices = mesh.num_vertices
        self.local = mesh.local_vertices
        self.interior = mesh.topology.interior
        self._x = None
        self._edges = None
        self._fields = None
        self._lengths = None
        self._host: dict = {}
        self._orders: dict = {}
        self._edge_orders: dict = {}
        self._pieces = None
        self._scales: dict = {}
        self._store: dict = {}
        self._replays: dict = {}
        self._plans: OrderedDict = OrderedDict()
        self._unused = None
        self._grads = None
        self._state = None
        # a new token for every VNC-soft call: a backward pass may reuse what its forward call prepared while the
        # engine's token is still that call's (no other call has written the scratch since)
        self._soft_token = None
        # token -> a weak reference to what a caller still reads in a graph's outputs (:meth:`hold`)
        self._held: dict = {}

    def __repr__(self) -> str:
        return f"Engine({self.name!r}, V={self.num_vertices}, device={self.device.alias!r})"

    # --- what the engine owns ------------------------------------------------------------------------------------

    @property
    def x(self) -> wp.array:
        """(V,) vec3: the mesh's vertices relative to its centre on the device (read-only for every caller)."""
        if self._x is None:
            self._x = wp.array(self.local, dtype=wp.vec3, device=self.device)
        return self._x

    @property
    def edges(self) -> wp.array:
        """(Ei,) vec4i: the interior edges ``(a, b, c0, c1)``."""
        if self._edges is None:
            if self.interior.shape[0] == 0:
                raise MeshError(f"{self.name}: no interior edges (every edge has a single face); VNC is undefined")
            self._edges = wp.array(self.interior, dtype=wp.vec4i, device=self.device)
        return self._edges

    def own(self, x: wp.array) -> bool:
        """Whether ``x`` is the engine's own vertex array, whose derived arrays may be kept."""
        return x is self._x

    def pool(self, kind: str) -> _plan.Pool:
        """Scratch for a call that is not replayed."""
        return _plan.Pool(self.device, kind, self._store, self.tuning.pool_limit)

    def _replay(self) -> Replay | None:
        kind = "cuda" if self.device.is_cuda else "cpu"
        if kind not in replayed_kinds(self.tuning.replay) or self.device.is_capturing:
            return None
        stream = self.device.stream.cuda_stream if self.device.is_cuda else 0
        table = self._replays.get(stream)
        if table is None:
            table = self._replays[stream] = Replay(self.device, self.tuning.max_graphs)
        return table

    def graphs(self) -> list:
        """The keys of the graphs captured on the current stream."""
        stream = self.device.stream.cuda_stream if self.device.is_cuda else 0
        table = self._replays.get(stream)
        return [] if table is None else table.graphs()

    def hold(self, token: object, held) -> None:
        """Keep ``held`` (referenced weakly) while its owner reads the outputs of the VNC-soft call that gave ``token``
        in a graph's arrays: ``held.save()`` (which copies them out) runs before the engine's next VNC-soft call, the
        only kind whose scratch holds them (:class:`~vnc_warp._plan.Pool` keys its buffers by kind), unless
        :meth:`soft_gradient` with ``token`` comes first: it reads them on the device and calls ``held.release()``
        instead. An op whose backward pass may need them so copies them only when they are about to change."""
        self._held[token] = weakref.ref(held)

    def _save_held(self) -> None:
        for ref in self._held.values():
            held = ref()
            if held is not None:
                held.save()
        self._held.clear()

    def _release(self, token: object) -> None:
        ref = self._held.pop(token, None)
        held = ref() if ref is not None else None
        if held is not None:
            held.release()

    def _call(self, key: tuple, kind: str, run, *, copy: bool = True) -> list | tuple[list, bool]:
        """``run(pool, fresh)``'s outputs, replayed when possible, as arrays of the caller's own; with ``copy=False``
        ``(outputs, owned)`` instead, where outputs that are not ``owned`` belong to a graph: the caller copies them
        out (in its own way) before the next call on the engine's stream."""
        if self._held and kind == "soft":
            self._save_held()
        table = self._replay()
        if table is None:
            outs, fresh = run(self.pool(kind), True), True
        else:
            outs, fresh = table.call(key, kind, run, self.pool(kind))
        if not copy:
            return outs, fresh
        return outs if fresh else [wp.clone(o) for o in outs]

    def _unused_vec3(self) -> wp.array:
        """An empty vec3 2d array for a kernel argument a variant does not read."""
        if self._unused is None:
            self._unused = wp.empty((0, 0), dtype=wp.vec3, device=self.device)
        return self._unused

    def sorted_lengths(self) -> np.ndarray:
        """The interior edges' lengths of the own vertices on the host, sorted."""
        if self._lengths is None:
            e, v = self.interior, self.local
            self._lengths = np.sort(np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1).astype(np.float32))
        return self._lengths

    def host_bounds(self, x: wp.array, stats, lengths: bool = False) -> _plan.Bounds | None:
        """The :class:`~vnc_warp._plan.Bounds` of a call, from the host when ``x`` is the own vertices and the radii
        came from the host (``stats = (max, mean)``), else None. Without a read from the device the launches that
        follow are queued while the device still works on earlier ones."""
        if stats is None or not self.own(x):
            return None
        if "bbox" not in self._host:
            self._host["bbox"] = (self.local.min(0).astype(np.float64), self.local.max(0).astype(np.float64))
        lo, hi = self._host["bbox"]
        lmax = lmean = 0.0
        if lengths:
            L = self.sorted_lengths()
            # float32 lengths on the device may round up past the host's: one part in 1e6 of slack
            lmax = float(L[-1]) * (1.0 + 1e-6)
            if "lmean" not in self._host:
                self._host["lmean"] = float(L.mean(dtype=np.float64))
            lmean = self._host["lmean"]
        return _plan.Bounds(lo, hi, float(stats[0]), float(stats[1]), lmax, lmean)

    def fields(self, x: wp.array, *, requires_grad: bool = False, pool: _plan.Pool | None = None,
               keep: bool = False) -> EdgeFields:
        """The edge fields of positions ``x`` (:func:`kernels.vnc_terms.edge_geometry`; scratch from ``pool`` unless
        they need gradients). ``keep``: those of the own vertices, computed once and kept (the caller only reads
        them)."""
        device = x.device
        rg = requires_grad or x.requires_grad
        if keep and not rg and self.own(x):
            if self._fields is None:
                if device.is_capturing:  # arrays made while capturing hold values only once the graph runs
                    return self.fields(x, pool=pool)
                self._fields = self.fields(x)
            return self._fields
        edges = self.edges
        ne = edges.shape[0]
        if rg:
            pool = None

        def new(dtype):
            return pool.empty(ne, dtype) if pool is not None else wp.empty(ne, dtype=dtype, device=device,
                                                                           requires_grad=rg)

        f = EdgeFields(edges, new(wp.vec3), new(wp.float32), new(wp.float32), new(wp.vec3))
        wp.launch(edge_geometry, dim=ne, inputs=[x, edges], outputs=[f.mid, f.length, f.angle, f.normal],
                  device=device)
        return f

    def _check_values(self, x: wp.array, radius: wp.array, *, host_checked: bool = False) -> None:
        """Refuse NaN or infinite positions and scales that are not positive and finite, given on the device (the grid
        traversals check them while reading their bounds; the BVH one calls this). ``host_checked``: the scales came
        from the host, where :func:`per_point` checked them; with the mesh's own vertices, checked when it was built,
        nothing is then reduced and read back."""
        if not (host_checked and self.own(x)):
            _plan.bounds(x, radius)

    def positions(self, positions) -> wp.array:
        """``positions`` checked against the mesh, or the own vertices (None)."""
        if positions is None:
            return self.x
        if not isinstance(positions, wp.array) or positions.dtype != wp.vec3:
            raise TypeError("positions must be a wp.array of wp.vec3")
        if positions.shape[0] != self.num_vertices:
            raise ValueError(f"positions has {positions.shape[0]} rows, the mesh {self.num_vertices} vertices")
        if positions.device != self.device:
            raise ValueError(f"positions live on {positions.device}, the engine on {self.device}")
        return positions

    # --- plans of positions given on the device ------------------------------------------------------------------

    def _moving(self, key: tuple, x: wp.array, tau, bounds_of) -> _Moving:
        """The plan ``key`` for the positions ``x`` (and scales ``tau``), loaded with them: the kept one, unless the
        bounds measured at its last call call for another; a new plan reads the bounds ``bounds_of(x, radius)``
        (``radius``: the scales on the device) now."""
        t = self.tuning
        plan = self._kept(key)
        if plan is None:
            radius = per_point(tau, self.num_vertices, self.device, "tau")
            bounds, strategy = bounds_of(x, radius)
            plan = _Moving(self, key, bounds, strategy, host_scalar(tau, "tau") is None)
            self._plans[key] = plan
            while len(self._plans) > t.max_graphs:
                self._forget(next(iter(self._plans.values())))
        self._plans.move_to_end(key)
        plan.load(x, tau)
        return plan

    def _kept(self, key: tuple) -> _Moving | None:
        """The plan ``key`` if it exists and the bounds measured at its last call do not call for another."""
        plan = self._plans.get(key)
        if plan is not None:
            s = plan.poll()
            if s is not None and plan.drifted(s, self.tuning):
                self._forget(plan)
                return None
            self._plans.move_to_end(key)
        return plan

    def _forget(self, plan: _Moving) -> None:
        self._plans.pop(plan.key, None)
        for table in self._replays.values():
            table.drop(lambda k: len(k) > 1 and k[1] is plan)

    # --- VNC-soft, Eq. (3) ---------------------------------------------------------------------------------------

    def vnc_soft(self, tau, *, kappa: float = 6.0, positions: wp.array | None = None, tape: wp.Tape | None = None,
                 strategy: str = "auto") -> tuple[wp.array, wp.array]:
        """VNC-soft, Eq. (3), per mesh vertex (:func:`vnc_warp.vnc_soft` on a Mesh): ``(H, n)``, (V,) float32 and (V,)
        vec3 arrays of the caller's own.

        Args:
            tau: a positive scalar or (V,) scales (NumPy, torch or a float32 ``wp.array``), mesh units.
            kappa: cut-off ratio, ``sigma = tau / kappa``.
            positions: (V,) vec3 positions on the engine's device (default: the mesh's own vertices).
            tape: a ``wp.Tape`` being recorded (``positions`` requiring gradients).
            strategy: "auto", "grid", "dense" or "bvh".
        """
        kappa = check_kappa(kappa, soft=True)
        _plan.check_strategy(strategy)
        x = self.positions(positions)
        self._soft_token = None
        if tape is not None and not x.requires_grad:
            raise ValueError("vnc_soft(tape=...) needs positions given as a wp.array with requires_grad=True")
        t = host_scalar(tau, "tau")
        if tape is not None or strategy == "bvh":
            outputs, f, backward, _ = self._soft(x, tau, kappa, strategy,
                                                 None if tape is not None else self.pool("soft"), True)
            if tape is not None:
                tape.record_func(backward=backward, arrays=[outputs[3], outputs[4], f.mid, f.length, f.angle,
                                                            f.normal])
            return outputs[3], outputs[4]
        if positions is not None:
            return tuple(self._soft_moving(x, tau, kappa, strategy)[:2])
        if t is not None:
            # a call fixed by its arguments: replayed from a captured graph from its third time on
            return tuple(self._call(("soft", t, kappa, strategy), "soft",
                                    lambda pool, fresh: self._soft(x, t, kappa, strategy, pool, fresh)[0][3:]))
        return tuple(self._soft(x, tau, kappa, strategy, self.pool("soft"), True)[0][3:])

    def _soft_bounds(self, strategy: str):
        def bounds_of(x, radius):
            b = _plan.bounds(x, radius)
            return b, _plan.resolve(strategy, self.device, b, b.rmean, self.num_vertices, self.edges.shape[0],
                                    self.tuning)
        return bounds_of

    def _soft_moving(self, x: wp.array | _Moving, tau, kappa: float, strategy: str, packed: int = 0, *,
                     grad: bool = False, copy: bool = True) -> list | tuple[list, bool]:
        """VNC-soft at positions ``x`` on the device through a plan: ``[H, n]``, or (``packed``: 9 or 24) one
        (V, packed) array of ``(H, n, N, D, S)`` per vertex (the torch op's outputs and what its backward pass reads),
        and in a row of 24 the moments of the vertex adjoint (:func:`kernels.vnc_sums.reduce_moments`). ``grad``: a
        backward pass follows (it reuses what this call leaves). ``x`` may be the plan itself (:meth:`soft_plan`), its
        positions written by the caller; ``copy``: as for :meth:`_call`."""
        t = host_scalar(tau, "tau")
        if isinstance(x, _Moving):
            plan = x
            plan.load(None, tau)
        else:
            plan = self._moving(self._soft_key(kappa, t, strategy), x, tau, self._soft_bounds(strategy))

        def run(pool, fresh):
            outputs, f, _, prep = self._soft(plan.x, plan.tau if t is None else t, kappa, plan.strategy, pool, fresh,
                                             bounds=plan.bounds, moments=packed > 9)
            plan.measure(plan.tau, copy_out=not fresh)
            if not packed:
                return outputs[3:]
            # only the torch op's (packed) calls leave what a backward pass reuses: a replayed call runs none of this,
            # so what an unpacked call of the same plan prepared must not stand in for it
            plan.prep = (f, prep, outputs[:3]) if grad else None
            out = _plan.empty(None if fresh else pool, self.device, (self.num_vertices, packed), wp.float32)
            wp.launch(_s.pack_soft_state, dim=self.num_vertices,
                      inputs=[outputs[3], outputs[4], *outputs[:3], prep[-1] if packed > 9 else self._unused_vec3()],
                      outputs=[out], device=self.device)
            return [out]

        self._soft_token = None
        outs, fresh = self._call(("soft-x", plan, packed, grad), "soft", run, copy=False)
        plan.fetch(copied=not fresh)
        self._soft_token = plan.token = _Token(plan, tau, kappa) if grad else None
        if copy:
            return outs if fresh else [wp.clone(o) for o in outs]
        return outs, fresh

    @staticmethod
    def _soft_key(kappa: float, t: float | None, strategy: str = "auto") -> tuple:
        return ("soft", strategy, kappa, "array" if t is None else t)

    def _soft(self, x: wp.array, tau, kappa: float, strategy: str, pool: _plan.Pool | None, fresh: bool, *,
              bounds: _plan.Bounds | None = None, moments: bool = False):
        """The launches of one VNC-soft call: ``([num, den, nsum, H, n], edge fields, backward closure, traversal)``,
        the traversal ``(tau, cells, groups, edge records, moments)`` (None for the BVH).

        ``pool``: scratch (None: new arrays, kept by the backward closure); ``fresh``: ``H`` and ``n`` are new arrays
        (else from ``pool``: a captured call's outputs); ``bounds``: a plan's (else from the host or the device);
        ``moments`` (implied by positions that require gradients): also the (5, V) moments the vertex adjoint reads
        (:func:`kernels.vnc_sums.reduce_moments`; the grid and dense traversals)."""
        device = self.device
        V = self.num_vertices
        rg = x.requires_grad
        tau_arr = per_point(tau, V, device, "tau", pool)
        f = self.fields(x, pool=pool)
        outputs = [_plan.empty(pool, device, V, wp.float32), _plan.empty(pool, device, V, wp.float32),
                   _plan.empty(pool, device, V, wp.vec3)]
        if fresh:
            outputs += [wp.empty(V, dtype=wp.float32, device=device, requires_grad=rg),
                        wp.empty(V, dtype=wp.vec3, device=device, requires_grad=rg)]
        else:
            outputs += [pool.empty(V, wp.float32), pool.empty(V, wp.vec3)]
        if strategy == "bvh":
            self._check_values(x, tau_arr, host_checked=not isinstance(tau, wp.array))
            return outputs, f, self._soft_bvh(x, tau_arr, kappa, f, outputs), None
        b = bounds or self.host_bounds(x, radius_stats(tau)) or _plan.bounds(x, tau_arr)
        concrete = _plan.resolve(strategy, device, b, b.rmean, V, f.mid.shape[0], self.tuning)
        backward, prep = self._soft_cells(x, tau_arr, kappa, f, outputs, b, concrete, pool, bounds is not None,
                                          moments or (rg and not self.tuning.scatter_on(device.is_cuda)))
        return outputs, f, backward, (tau_arr, *prep)

    def _midpoint_bvh(self, f: EdgeFields) -> wp.Bvh:
        ne = f.mid.shape[0]
        lowers = wp.empty(ne, dtype=wp.vec3, device=self.device)
        uppers = wp.empty(ne, dtype=wp.vec3, device=self.device)
        wp.launch(_ref.midpoint_bounds, dim=ne, inputs=[f.mid], outputs=[lowers, uppers], device=self.device,
                  record_tape=False)
        return wp.Bvh(lowers, uppers)

    def _segment_bvh(self, x: wp.array, f: EdgeFields) -> wp.Bvh:
        ne = f.edges.shape[0]
        lowers = wp.empty(ne, dtype=wp.vec3, device=self.device)
        uppers = wp.empty(ne, dtype=wp.vec3, device=self.device)
        wp.launch(_ref.segment_bounds, dim=ne, inputs=[x, f.edges], outputs=[lowers, uppers], device=self.device,
                  record_tape=False)
        return wp.Bvh(lowers, uppers)

    def _soft_bvh(self, x, tau_arr, kappa, f, outputs):
        """VNC-soft through the reference kernels (a BVH query per vertex); returns the backward closure."""
        device = self.device
        V = x.shape[0]
        bvh = self._midpoint_bvh(f)
        wp.launch(_ref.soft_forward, dim=V, inputs=[x, tau_arr, kappa, bvh.id, f.mid, f.length, f.angle, f.normal],
                  outputs=outputs, device=device, record_tape=False)
        num, den, nsum, H, n = outputs

        def backward():
            wp.launch(_ref.soft_backward, dim=V,
                      inputs=[x, tau_arr, kappa, bvh.id, f.mid, f.length, f.angle, f.normal, num, den, nsum, H.grad,
                              n.grad],
                      outputs=[x.grad, f.mid.grad, f.length.grad, f.angle.grad, f.normal.grad], device=device,
                      record_tape=False)

        return backward

    def _soft_prepare(self, x, tau_arr, f: EdgeFields, b: _plan.Bounds, strategy: str, pool):
        """The grid (or dense) traversal of VNC-soft: cells of the edges, groups of the vertices and the packed edge
        records."""
        device = self.device
        cells, groups = _plan.plan(x, tau_arr, f.mid, b, strategy, b.rmean, self.tuning,
                                   max_per_thread=self.tuning.qb, orders=self._orders, pool=pool)
        E = f.mid.shape[0]
        pos = _plan.empty(pool, device, E, wp.vec4)
        val = _plan.empty(pool, device, E, wp.vec4)
        wp.launch(_g.pack_soft_sources, dim=E, inputs=[cells.order, f.mid, f.length, f.angle, f.normal],
                  outputs=[pos, val], device=device, record_tape=False)
        return cells, groups, pos, val

    def _soft_cells(self, x, tau_arr, kappa, f, outputs, b, strategy, pool, moving: bool, moments: bool):
        """VNC-soft through the grid or dense traversal; returns the backward closure (same pairs, gathered) and the
        traversal ``(cells, groups, edge records, moments)``. ``moving``: ``b`` are a plan's bounds, made for earlier
        positions (the kernels then clamp to its grid); ``moments``: also the (5, V) moments of the vertex adjoint
        (else None)."""
        device = self.device
        V = x.shape[0]
        cells, groups, pos, val = self._soft_prepare(x, tau_arr, f, b, strategy, pool)
        shape = (groups.splits, groups.padded)
        parts = [_plan.empty(pool, device, shape, dt) for dt in (wp.float32, wp.float32, wp.vec3)]
        if moments:
            parts.append(_plan.empty(pool, device, (5 * groups.splits, groups.padded), wp.vec3))
            mom = _plan.empty(pool, device, (5, V), wp.vec3)
        else:
            parts.append(self._unused_vec3())
            mom = None
        num, den, nsum, H, n = outputs
        kernel = _s.soft_cells_kernel(groups.per_thread, self.tuning.cull_on(device.is_cuda), moving=moving,
                                      moments=moments)
        wp.launch(kernel, dim=groups.dim, inputs=[x, tau_arr, kappa, *groups.args(cells), pos, val],
                  outputs=parts, device=device, record_tape=False, block_dim=self.tuning.block_dim)
        wp.launch(_s.reduce_sums, dim=V, inputs=[groups.order, *parts[:3]], outputs=outputs, device=device,
                  record_tape=False)
        if moments:
            wp.launch(_s.reduce_moments, dim=(5, V), inputs=[groups.order, parts[3]], outputs=[mom], device=device,
                      record_tape=False)

        def backward():
            self._soft_adjoint(x, tau_arr, kappa, f, mom, num, den, nsum, H.grad, n.grad, x.grad,
                               [f.mid.grad, f.length.grad, f.angle.grad, f.normal.grad], b, strategy, None, moving)

        return backward, (cells, groups, pos, val, mom)

    def _soft_adjoint(self, x, tau_arr, kappa, f, moments, num, den, nsum, H_grad, n_grad, x_grad, edge_grads, b,
                      strategy, pool, moving: bool) -> None:
        """The adjoint of the grid (or dense) VNC-soft over the forward's pairs: ``x_grad`` += the vertices' part from
        the forward's ``moments`` in one pass over the vertices (:func:`kernels.vnc_sums.vertex_gradient`; None: added
        by the edge adjoint's pairs, ``Tuning.vertex_scatter``), ``edge_grads`` (mid, length, angle, normal) += the
        edges' (:func:`kernels.vnc_sums.soft_edge_adjoint_kernel`, a gather per edge over the vertices that reach
        it)."""
        device = self.device
        t = self.tuning
        V, E = x.shape[0], f.mid.shape[0]
        if moments is not None:
            wp.launch(_s.vertex_gradient, dim=V, inputs=[tau_arr, kappa, num, den, nsum, moments, H_grad, n_grad],
                      outputs=[x_grad], device=device, record_tape=False)
        # edges gather over the vertices whose ball (radius tau_k) reaches their midpoint: each edge's reach is the
        # largest radius, taken on the device (a plan's bounds may be older than the radii)
        top = _plan.zeros(pool, device, 1, wp.float32)
        wp.launch(_s.largest, dim=V, inputs=[tau_arr], outputs=[top], device=device, record_tape=False)
        reach = _plan.empty(pool, device, E, wp.float32)
        wp.launch(_s.broadcast, dim=E, inputs=[top], outputs=[reach], device=device, record_tape=False)
        vcells, egroups = _plan.plan(f.mid, reach, x, b, strategy, b.rmax, t, max_per_thread=t.qb,
                                     orders=self._edge_orders, pool=pool)
        vpos, vcoef, vgs = (_plan.empty(pool, device, V, wp.vec4) for _ in range(3))
        wp.launch(_s.pack_vertex_adjoints, dim=V,
                  inputs=[vcells.order, x, tau_arr, kappa, num, den, nsum, H_grad, n_grad],
                  outputs=[vpos, vcoef, vgs], device=device, record_tape=False)
        shape = (egroups.splits, egroups.padded)
        eparts = [_plan.empty(pool, device, shape, dt) for dt in (wp.float32, wp.float32, wp.vec3, wp.vec3)]
        kernel = _s.soft_edge_adjoint_kernel(egroups.per_thread, t.cull_on(device.is_cuda), moving, moments is None)
        wp.launch(kernel, dim=egroups.dim,
                  inputs=[f.mid, f.angle, f.normal, reach, kappa, *egroups.args(vcells), vpos, vcoef, vgs],
                  outputs=[*eparts, f.length, vcells.order, x_grad], device=device, record_tape=False,
                  block_dim=t.block_dim)
        mid_g, length_g, angle_g, normal_g = edge_grads
        wp.launch(_s.reduce_edge_grads, dim=E, inputs=[egroups.order, f.length, f.angle, f.normal, *eparts],
                  outputs=[angle_g, length_g, normal_g, mid_g], device=device, record_tape=False)

    def soft_plan(self, tau, kappa: float) -> _Moving | None:
        """The kept plan of :meth:`soft_state` calls with these scales (None: none yet, or the positions of its last
        call drifted past it). A caller may write the next positions into its ``x`` ((V,) vec3, relative to the
        centre) and pass the plan to :meth:`soft_state` in their place: a replayed call then copies nothing in."""
        return self._kept(self._soft_key(kappa, host_scalar(tau, "tau")))

    @property
    def soft_grads(self) -> wp.array:
        """(V, 4) float32: where :meth:`soft_gradient` reads the upstream gradients ``(dL/dH, dL/dn)`` when it is given
        none (the caller wrote them here; every backward graph of the engine reads this one array)."""
        if self._grads is None:
            self._grads = wp.empty((self.num_vertices, 4), dtype=wp.float32, device=self.device)
        return self._grads

    def soft_state(self, x: wp.array | _Moving, tau, kappa: float, *, grad: bool = True,
                   copy: bool = True) -> tuple[wp.array, object] | tuple[wp.array, object, bool]:
        """VNC-soft at device positions ``x`` for a differentiable op: ``(state, token)``, ``state`` a (V, 24) float32
        array of the caller's own, ``(H, n, N, D, S)`` and the 15 moments of the vertex adjoint per vertex (a (V, 9)
        array of the sums where the backward pass adds the vertices' part itself, ``Tuning.vertex_scatter``), for
        :meth:`soft_gradient` with ``token`` (``grad=False``: a (V, 9) array of the sums only, and no token: for a
        forward pass that no backward pass follows). ``x`` may be a :meth:`soft_plan` holding the positions.
        ``copy=False``: ``(state, token, owned)``, where a state that is not ``owned`` belongs to a graph (copy it out
        before the next call, or :meth:`hold` it)."""
        kappa = check_kappa(kappa, soft=True)
        if not isinstance(x, _Moving):
            x = self.positions(x)
        moments = grad and not self.tuning.scatter_on(self.device.is_cuda)
        outs = self._soft_moving(x, tau, kappa, "auto", packed=24 if moments else 9, grad=grad, copy=copy)
        if copy:
            return outs[0], self._soft_token
        return outs[0][0], self._soft_token, outs[1]

    def soft_gradient(self, x, tau, kappa: float, state, grads: wp.array | None, token: object = None, *,
                      copy: bool = True) -> wp.array | tuple[wp.array, bool]:
        """The gradient of VNC-soft with respect to the positions ``x`` of a :meth:`soft_state` call that gave
        ``(state, token)``, for the upstream gradients ``grads`` ((V, 4) float32: ``dL/dH``, ``dL/dn``; None: the
        caller wrote them into :attr:`soft_grads`): (V,) vec3, an array of the caller's own (``copy=False``:
        ``(gx, owned)`` as for :meth:`soft_state`). The vertices' part comes from the moments of the forward call
        (one pass over the vertices; or from the edges' pairs, ``Tuning.vertex_scatter``), the edges' from a gather
        over the plan of the forward call, then the edge fields' adjoint, replayed from a graph; when no VNC-soft call
        ran on the engine since (its token is still ``token``), on the edge fields, sums and moments that call left on
        the device, else on those of ``x`` and ``state`` (either may be a function giving the array: it is called only
        then)."""
        replayed = self._replayed_gradient(token, tau, kappa, grads)
        if replayed is not None:
            return wp.clone(replayed) if copy else (replayed, False)
        kappa = check_kappa(kappa, soft=True)
        t = host_scalar(tau, "tau")
        key = self._soft_key(kappa, t)
        V = self.num_vertices
        plan = self._plans.get(key)
        reuse = (plan is not None and token is not None and plan.token is token and self._soft_token is token
                 and plan.prep is not None)
        if reuse:  # the forward call's state is not read, nor kept for later
            self._release(token)
        else:
            plan = self._moving(key, self.positions(x() if callable(x) else x), tau, self._soft_bounds("auto"))
            # the plan's positions are no longer those of the last forward call: its backward pass must not reuse
            self._soft_token = None
        grads_in = self.soft_grads
        if grads is not None:
            wp.copy(grads_in, grads)

        def adjoint(pool, fresh, f, prep, sums, H_grad, n_grad):
            device = self.device
            E = f.mid.shape[0]
            gx = _plan.zeros(None if fresh else pool, device, V, wp.vec3)
            edge_grads = [_plan.zeros(pool, device, E, dt) for dt in (wp.vec3, wp.float32, wp.float32, wp.vec3)]
            self._soft_adjoint(plan.x, prep[0], kappa, f, prep[-1], *sums, H_grad, n_grad, gx, edge_grads,
                               plan.bounds, plan.strategy, pool, True)
            wp.launch(edge_geometry, dim=E, inputs=[plan.x, f.edges], outputs=[f.mid, f.length, f.angle, f.normal],
                      adj_inputs=[gx, None], adj_outputs=edge_grads, adjoint=True, device=device)
            return [gx]

        if reuse:
            def run(pool, fresh):
                H_grad = _plan.empty(pool, self.device, V, wp.float32)
                n_grad = _plan.empty(pool, self.device, V, wp.vec3)
                wp.launch(_s.unpack_grads, dim=V, inputs=[grads_in], outputs=[H_grad, n_grad], device=self.device)
                f, prep, sums = plan.prep
                return adjoint(pool, fresh, f, prep, sums, H_grad, n_grad)

            outs = self._call(("soft-grad-reuse", plan), "soft-grad", run, copy=copy)
        else:
            held = state() if callable(state) else state
            if self._state is None or self._state.shape != held.shape:
                self._state = wp.empty(held.shape, dtype=wp.float32, device=self.device)
            state_in = self._state
            wp.copy(state_in, held)

            def run(pool, fresh):
                device = self.device
                tau_arr = per_point(plan.tau if t is None else t, V, device, "tau", pool)
                f = self.fields(plan.x, pool=pool)
                num, den, H_grad = (_plan.empty(pool, device, V, wp.float32) for _ in range(3))
                nsum, n_grad = (_plan.empty(pool, device, V, wp.vec3) for _ in range(2))
                moments = _plan.empty(pool, device, (5, V), wp.vec3) if state_in.shape[1] > 9 else None
                wp.launch(_s.unpack_soft_state, dim=V, inputs=[state_in, grads_in],
                          outputs=[num, den, nsum, moments, H_grad, n_grad], device=device)
                return adjoint(pool, fresh, f, (tau_arr, moments), (num, den, nsum), H_grad, n_grad)

            outs = self._call(("soft-grad", plan), "soft-grad", run, copy=copy)
        return outs[0] if copy else (outs[0][0], outs[1])

    def _replayed_gradient(self, token, tau, kappa, grads: wp.array | None) -> wp.array | None:
        """:meth:`soft_gradient`'s common case at the host cost of a graph launch: the backward pass of the engine's
        last VNC-soft call, given the same ``tau`` object and ``kappa``, once its graph is captured (the gradient, a
        graph's output); else None (nothing done)."""
        if not isinstance(token, _Token) or token is not self._soft_token or token.tau is not tau or (
                token.kappa != kappa):
            return None
        plan = token.plan
        if plan.token is not token or plan.prep is None or self._plans.get(plan.key) is not plan:
            return None
        table = self._replay()
        key = ("soft-grad-reuse", plan)
        if table is None or not table.captured(key):
            return None
        self._release(token)
        if grads is not None:
            wp.copy(self.soft_grads, grads)
        return table.launch(key)[0]

    # --- VNC-hard and the integrated measure, Eqs. (1)-(2) -------------------------------------------------------

    def vnc_hard(self, tau, *, kappa: float | None = 6.0, strategy: str = "auto") -> tuple[wp.array, wp.array]:
        """VNC-hard, Eq. (2), per mesh vertex (:func:`vnc_warp.vnc_hard` on a Mesh): ``(H, n)``."""
        k = check_kappa(kappa, soft=False)
        _plan.check_strategy(strategy)
        t = host_scalar(tau, "tau")
        if t is not None and strategy != "bvh":
            return tuple(self._call(("hard", t, k, strategy), "ball",
                                    lambda pool, fresh: self._ball_at_vertices(t, k, strategy, pool, fresh)[3:]))
        return tuple(self._ball_at_vertices(tau, k, strategy, self.pool("ball"), True)[3:])

    def integrated(self, radius, points=None, *, strategy: str = "auto") -> wp.array:
        """Eq. (1) at the vertices or at ``points`` ((P, 3) float32 relative to the mesh's origin, on the host):
        ``1/2 sum alpha delta l``, a (V,) or (P,) float32 array (:func:`vnc_warp.integrated_mean_curvature`)."""
        _plan.check_strategy(strategy)
        device = self.device
        t = host_scalar(radius, "radius")
        if points is None and t is not None and strategy != "bvh":
            def run(pool, fresh):
                num = self._ball_at_vertices(t, None, strategy, pool, fresh)[0]
                out = _plan.empty(None if fresh else pool, device, self.num_vertices, wp.float32)
                wp.launch(_s.scaled_copy, dim=self.num_vertices, inputs=[num, 0.5], outputs=[out], device=device)
                return [out]

            return self._call(("integrated", t, strategy), "ball", run)[0]
        if points is None:
            pts = self.x
        else:
            P = points.shape[0]
            if P == 0:
                per_point(radius, 0, device, "radius")
                return wp.empty(0, dtype=wp.float32, device=device)
            pts = wp.array(points, dtype=wp.vec3, device=device)
        P = pts.shape[0]
        r = per_point(radius, P, device, "radius")
        g = wp.zeros(P, dtype=wp.float32, device=device)
        num = self._ball(pts, r, g, strategy, radius_stats(radius), self.pool("ball"), True)[0]
        out = wp.empty(P, dtype=wp.float32, device=device)
        wp.launch(_s.scaled_copy, dim=P, inputs=[num, 0.5], outputs=[out], device=device)
        return out

    def _ball_at_vertices(self, tau, kappa: float | None, strategy: str, pool, fresh: bool) -> list:
        """The launches of VNC-hard / Eq. (1) at the own vertices: ``[num, den, nsum, H, n]``; ``kappa=None``: w = 1."""
        V = self.num_vertices
        radius = per_point(tau, V, self.device, "tau", pool)
        g = pool.empty(V, wp.float32)
        wp.launch(_s.gaussian_factors, dim=V, inputs=[radius, 0.0 if kappa is None else kappa], outputs=[g],
                  device=self.device)
        return self._ball(self.x, radius, g, strategy, radius_stats(tau), pool, fresh)

    def _piece_capacity(self, piece: float) -> int:
        """Slots for the pieces of the own edges no longer than ``piece`` (:func:`_plan.piece_capacity`, once per
        piece length)."""
        key = ("piece_capacity", piece)
        if key not in self._host:
            self._host[key] = _plan.piece_capacity(self.sorted_lengths(), piece)
        return self._host[key]

    def _kept_pieces(self, x: wp.array, f: EdgeFields) -> dict | None:
        """The pieces of the own edges for single-scale ball traversals on the CPU (``tuning.cpu_pieces``): sorted once
        and kept, whatever the radius (as trimesh keeps an R-tree of its edges), with the boxes of their runs. While
        a graph is captured (its arrays only hold values once it runs) only pieces kept before, else None."""
        if self._pieces is None and not self.device.is_capturing:
            piece, cell = self.tuning.cpu_pieces
            b = self.host_bounds(x, (0.0, 0.0), lengths=True)
            P = piece * b.lmean
            grid = _plan.piece_grid(x, f.edges, f.length, b, "grid", self.tuning, piece=P, cell=cell * b.lmean,
                                    fine=True, capacity=self._piece_capacity(P))
            src = self._piece_sources(x, f, grid, None)
            src["chunk_lo"], src["chunk_hi"] = self._chunk_boxes(src["seg_m"], src["seg_h"], grid.cells.first,
                                                                 grid.cells.first, None)
            self._pieces = src
        return self._pieces

    def _piece_sources(self, x: wp.array, f: EdgeFields, grid: _plan.PieceGrid, pool) -> dict:
        """The records of the sorted pieces of ``grid`` (:func:`kernels.vnc_grid.pack_piece_sources`)."""
        device = self.device
        n = grid.pieces.capacity
        seg_m, seg_h, val = (_plan.empty(pool, device, n, wp.vec4) for _ in range(3))
        p = grid.pieces
        wp.launch(_g.pack_piece_sources, dim=n,
                  inputs=[grid.cells.order, p.piece_edge, p.piece_index, p.counts, x, f.edges, f.angle, f.normal],
                  outputs=[seg_m, seg_h, val], device=device, record_tape=False)
        return {"grid": grid, "seg_m": seg_m, "seg_h": seg_h, "val": val}

    def _chunk_boxes(self, seg_m, seg_h, start, end, pool) -> tuple[wp.array, wp.array]:
        """The boxes of the runs of ``tuning.chunk`` records a chunked traversal reads, from the first record
        ``start[0]`` (None: no traversal tests runs; empty boxes) to ``end[-1]``."""
        chunk = self.tuning.chunk
        nchunks = -(-seg_m.shape[0] // chunk) if start is not None else 0
        lo, hi = (_plan.empty(pool, self.device, nchunks, wp.vec3) for _ in range(2))
        if nchunks:
            # few threads, each a serial loop: blocks of one warp spread them over every multiprocessor
            wp.launch(_g.chunk_boxes_kernel(chunk), dim=nchunks, inputs=[seg_m, seg_h, start, end], outputs=[lo, hi],
                      device=self.device, block_dim=32)
        return lo, hi

    def _ball(self, points, radius, g, strategy: str, stats, pool, fresh: bool, *, x: wp.array | None = None,
              save: bool = False):
        """Eqs. (1)-(2) sums per query point over the edges of positions ``x`` (default: the own vertices):
        ``[num, den, nsum, H, n]`` (``H``, ``n`` normalized as in Eq. (2)); with ``save``, also what the adjoint
        reads (:meth:`hard_gradient`).

        ``points is x`` marks the vertices as the queries: their Morton order is then kept. ``stats``: ``(max, mean)``
        of ``radius`` when known on the host. ``fresh``: ``H`` and ``n`` are new arrays (else from ``pool``)."""
        _plan.check_strategy(strategy)
        device = self.device
        t = self.tuning
        x = self.x if x is None else x
        own = self.own(x)
        # on the (one-thread) CPU the own edges' fields are kept, as their pieces are (_kept_pieces)
        f = self.fields(x, pool=pool, keep=device.is_cpu)
        P = points.shape[0]
        outputs = [_plan.empty(pool, device, P, dt) for dt in (wp.float32, wp.float32, wp.vec3)]
        outputs += [_plan.empty(None if fresh else pool, device, P, dt) for dt in (wp.float32, wp.vec3)]
        if strategy == "bvh":
            self._check_values(x, radius, host_checked=stats is not None)
            bvh = self._segment_bvh(x, f)
            wp.launch(_ref.ball_sums, dim=P, inputs=[points, radius, g, bvh.id, x, f.edges, f.mid, f.angle, f.normal],
                      outputs=outputs[:3], device=device)
            wp.launch(_ref.normalize_sums, dim=P, inputs=outputs[:3], outputs=outputs[3:], device=device)
            return outputs + ([{"bvh": bvh, "f": f, "x": x}] if save else [])
        E = f.mid.shape[0]
        host = self.host_bounds(x, stats, lengths=True)
        b = host or _plan.bounds(x, radius, f.length)
        # an edge crosses the ball only if its midpoint is within radius + L / 2
        concrete = _plan.resolve(strategy, device, b, b.rmean + 0.5 * b.lmax, P, E, t)
        reach = _plan.ball_reach(b)
        orders = self._orders if points is x else None
        kept = (self._kept_pieces(x, f) if device.is_cpu and t.cpu_pieces is not None and own
                and _plan.uses_pieces(concrete, b, t, any_length=True) else None)
        if kept is not None or _plan.uses_pieces(concrete, b, t):
            # pieces of the edges
            if kept is not None:
                src = kept
            else:
                piece = _plan.piece_length(b, t)
                capacity = self._piece_capacity(piece) if own else _plan.piece_bound(b, E, piece)
                grid = _plan.piece_grid(x, f.edges, f.length, b, concrete, t, capacity=capacity,
                                        max_per_thread=t.qb, pool=pool)
                src = self._piece_sources(x, f, grid, pool)
            cells = src["grid"].cells
            groups = _plan.piece_groups(points, radius, src["grid"], b, t, max_per_thread=t.qb, orders=orders,
                                        pool=pool)
            seg_m, seg_h, val = src["seg_m"], src["seg_h"], src["val"]
            ids = ("pieces", src["grid"])
        else:
            src = None
            cells, groups = _plan.edge_plan(points, radius, f.mid, b, concrete, t, max_per_thread=t.qb,
                                            orders=orders, pool=pool)
            seg_m, seg_h, val = (_plan.empty(pool, device, E, wp.vec4) for _ in range(3))
            wp.launch(_g.pack_ball_sources, dim=E, inputs=[cells.order, x, f.edges, f.angle, f.normal],
                      outputs=[seg_m, seg_h, val], device=device, record_tape=False)
            ids = ("edges", cells)
        variant = _plan.ball_variant(t, concrete, groups.per_thread, reach, cells.one_cell, device.is_cuda)
        parts = [_plan.empty(pool, device, (groups.splits, groups.padded), dt)
                 for dt in (wp.float32, wp.float32, wp.vec3)]
        if src is not None and "chunk_lo" in src:
            chunk_lo, chunk_hi = src["chunk_lo"], src["chunk_hi"]  # kept with the pieces
        else:
            chunk_lo, chunk_hi = self._chunk_boxes(seg_m, seg_h, cells.first if variant["chunks"] else None,
                                                   cells.first, pool)
        wp.launch(_s.ball_cells_kernel(**variant), dim=groups.dim,
                  inputs=[points, radius, g, *groups.args(cells), seg_m, seg_h, val, chunk_lo, chunk_hi,
                          groups.splits],
                  outputs=parts, device=device, block_dim=t.block_dim)
        wp.launch(_s.reduce_sums, dim=P, inputs=[groups.order, *parts], outputs=outputs, device=device)
        if save:
            outputs.append({"f": f, "x": x, "cells": cells, "groups": groups, "seg_m": seg_m, "seg_h": seg_h,
                            "ids": ids})
        return outputs

    def hard_state(self, x: wp.array, tau, kappa: float | None) -> list:
        """VNC-hard (Eq. 2) at device positions ``x`` (its own vertices as the ball centres) for a differentiable
        op: ``[num, den, nsum, H, n, state]``, new arrays; ``state`` is what :meth:`hard_gradient` reads. Not
        replayed: its bounds are read from the device (the pieces of the edges depend on their lengths)."""
        k = check_kappa(kappa, soft=False)
        x = self.positions(x)
        V = self.num_vertices
        radius = per_point(tau, V, self.device, "tau")
        g = wp.empty(V, dtype=wp.float32, device=self.device)
        wp.launch(_s.gaussian_factors, dim=V, inputs=[radius, 0.0 if k is None else k], outputs=[g],
                  device=self.device)
        out = self._ball(x, radius, g, "auto", None, None, True, x=x, save=True)
        out[5].update(radius=radius, g=g)
        return out

    def hard_gradient(self, outputs: list, H_grad: wp.array, n_grad: wp.array) -> wp.array:
        """The gradient of VNC-hard with respect to the positions of a :meth:`hard_state` call (``outputs`` its
        result) for the upstream ``H_grad`` (V,) and ``n_grad`` (V,) vec3: (V,) vec3. Every pair's chord and weight
        is differentiated with respect to the ball's centre and the edge's ends
        (:func:`kernels.vnc_terms.ball_pair_adjoint`); the angles' and normals' gradients flow to the vertices
        through the edge fields' adjoint."""
        device = self.device
        num, den, nsum, _, _, state = outputs
        f, x, radius, g = state["f"], state["x"], state["radius"], state["g"]
        V, E = self.num_vertices, f.mid.shape[0]
        gx = wp.zeros(V, dtype=wp.vec3, device=device)
        angle_g = wp.zeros(E, dtype=wp.float32, device=device)
        normal_g = wp.zeros(E, dtype=wp.vec3, device=device)
        if "bvh" in state:
            gp = wp.zeros(V, dtype=wp.vec3, device=device)
            wp.launch(_ref.ball_backward, dim=V,
                      inputs=[x, radius, g, state["bvh"].id, x, f.edges, f.length, f.angle, f.normal, num, den, nsum,
                              H_grad, n_grad],
                      outputs=[gp, gx, angle_g, normal_g], device=device)
            wp.launch(_s.add_vec3, dim=V, inputs=[gp], outputs=[gx], device=device)
        else:
            kind, where = state["ids"]
            n = state["seg_m"].shape[0]
            ids = wp.empty(n, dtype=wp.int32, device=device)
            if kind == "pieces":
                wp.launch(_s.source_edges, dim=n, inputs=[where.cells.order, where.pieces.piece_edge], outputs=[ids],
                          device=device)
            else:
                wp.copy(ids, where.order)
            cells, grp = state["cells"], state["groups"]
            part = wp.zeros((grp.splits, grp.padded), dtype=wp.vec3, device=device)
            wp.launch(_s.ball_adjoint_cells, dim=(grp.splits, grp.padded),
                      inputs=[x, radius, g, *grp.args(cells), state["seg_m"], state["seg_h"], ids, x, f.edges,
                              f.length, f.angle, f.normal, num, den, nsum, H_grad, n_grad],
                      outputs=[part, gx, angle_g, normal_g], device=device)
            wp.launch(_s.reduce_add_vec3, dim=V, inputs=[grp.order, part], outputs=[gx], device=device)
        zero_mid = wp.zeros(E, dtype=wp.vec3, device=device)
        zero_len = wp.zeros(E, dtype=wp.float32, device=device)
        wp.launch(edge_geometry, dim=E, inputs=[x, f.edges], outputs=[f.mid, f.length, f.angle, f.normal],
                  adj_inputs=[gx, None], adj_outputs=[zero_mid, zero_len, angle_g, normal_g], adjoint=True,
                  device=device)
        return gx

    # --- scale curves, Eqs. (3)-(4) ------------------------------------------------------------------------------

    def _taus(self, taus: np.ndarray) -> wp.array:
        """The scales on the device, made once per list of scales (an upload cannot be part of a graph)."""
        key = tuple(float(v) for v in taus)
        arr = self._scales.get(key)
        if arr is None:
            arr = self._scales[key] = wp.array(np.asarray(taus, np.float32), dtype=wp.float32, device=self.device)
            while len(self._scales) > 4 * self.tuning.max_graphs:
                self._scales.pop(next(iter(self._scales)))
        return arr

    def scale_curve(self, taus: np.ndarray, variant: str = "soft", *, kappa: float | None = 6.0,
                    positions: wp.array | None = None, strategy: str = "auto") -> tuple[wp.array, wp.array]:
        """The VNC-Scale curves at the (ascending, checked) ``taus`` in one traversal per 16 scales: ``(H, mean)``,
        a (S, V) and a (S,) float32 array of the caller's own (:func:`vnc_warp.scale_curve` on a Mesh)."""
        k = check_kappa(kappa, soft=variant == "soft")
        _plan.check_strategy(strategy)
        taus = np.asarray(taus, dtype=np.float64)
        x = self.positions(positions)
        key = ("curve", variant, tuple(taus.tolist()), k, strategy)
        taus_wp = self._taus(taus)
        if strategy == "bvh" or (positions is not None and variant == "hard"):
            # (VNC-hard's traversal pads the balls by half the longest edge: no plan outlives the edges' lengths)
            return tuple(self._curve(x, taus, taus_wp, variant, k, strategy, self.pool("curve"), True))
        if positions is None:
            return tuple(self._call(key, "curve", lambda pool, fresh: self._curve(x, taus, taus_wp, variant, k,
                                                                                strategy, pool, fresh)))

        def bounds_of(x, radius):
            return _plan.bounds(x, radius), strategy

        plan = self._moving(key, x, float(taus[-1]), bounds_of)

        def run(pool, fresh):
            outs = self._curve(plan.x, taus, taus_wp, variant, k, strategy, pool, fresh, bounds=plan.bounds)
            plan.measure(None)
            return outs

        outs = self._call(("curve-x", plan), "curve", run)
        plan.fetch()
        return tuple(outs)

    def total_complexity(self, taus, *, kappa: float = 6.0, positions: wp.array | None = None) -> float:
        """``S = sum_k s(v_k)``: the VNC-AUC (Eq. 4 at ``tau_max``) of VNC-soft summed over the vertices, at
        ``positions`` (default: the own vertices); one read from the device."""
        taus = np.asarray(taus, dtype=np.float64)
        H, mean = self.scale_curve(taus, "soft", kappa=kappa, positions=positions)
        auc = wp.empty(self.num_vertices, dtype=wp.float32, device=self.device)
        wp.launch(_ks.scale_auc, dim=self.num_vertices, inputs=[H, mean, self._taus(taus)], outputs=[auc],
                  device=self.device)
        return ordered_sum(auc)

    def _curve(self, x, taus, taus_wp, variant, kappa, strategy, pool, fresh, bounds=None) -> list:
        """The launches of one scale curve: ``[H, mean]`` (new arrays when ``fresh``, else from ``pool``)."""
        device = self.device
        S, V = taus.size, self.num_vertices
        f = self.fields(x, pool=pool)
        H = _plan.empty(None if fresh else pool, device, (S, V), wp.float32)
        if strategy == "bvh":
            self._check_values(x, taus_wp)
            self._curve_bvh(x, f, taus_wp, variant, kappa, H)
        else:
            self._curve_cells(x, f, taus, taus_wp, variant, kappa, strategy, H, pool, bounds)
        mean = _plan.empty(None if fresh else pool, device, S, wp.float32)
        partial = _plan.empty(None if fresh else pool, device, (S, min(V, 256)), wp.float32)
        wp.launch(_ks.column_sums, dim=partial.shape, inputs=[H, 1.0 / V], outputs=[partial], device=device)
        wp.launch(_ks.row_sums, dim=S, inputs=[partial], outputs=[mean], device=device)
        return [H, mean]

    def _curve_bvh(self, x, f, taus_wp, variant, kappa, H):
        device = self.device
        S, V = H.shape
        num = wp.zeros((S, V), dtype=wp.float32, device=device)
        den = wp.zeros((S, V), dtype=wp.float32, device=device)
        k = 0.0 if kappa is None else float(kappa)
        if variant == "soft":
            bvh = self._midpoint_bvh(f)
            wp.launch(_ref.soft_multiscale, dim=V, inputs=[x, taus_wp, k, bvh.id, f.mid, f.length, f.angle],
                      outputs=[num, den], device=device)
        else:
            bvh = self._segment_bvh(x, f)
            wp.launch(_ref.ball_multiscale, dim=V, inputs=[x, taus_wp, k, bvh.id, x, f.edges, f.mid, f.angle],
                      outputs=[num, den], device=device)
        wp.launch(_ref.ratio2d, dim=(S, V), inputs=[num, den], outputs=[H], device=device)

    def _curve_cells(self, x, f, taus, taus_wp, variant, kappa, strategy, H, pool, bounds):
        device = self.device
        t = self.tuning
        S, V = H.shape
        E = f.mid.shape[0]
        soft = variant == "soft"
        tmax = float(taus[-1])
        if bounds is None:
            bounds = self.host_bounds(x, (tmax, tmax), lengths=not soft) or _plan.bounds(
                x, per_point(tmax, V, device, "tau", pool), None if soft else f.length)
        b = bounds
        pad = 0.0 if soft else 0.5 * b.lmax
        k = 0.0 if kappa is None else float(kappa)  # kappa = 0: unweighted scales
        # 32 sums per scale chunk and thread: fewer splits than a single-scale traversal
        splits = min(_plan.launch_shape(device, V, 1, 0.0, t)[1], 4)
        for offset in range(0, S, 16):
            tmax = float(taus[min(offset + 16, S) - 1])
            concrete = _plan.resolve(strategy, device, b, tmax + pad, V, E, t)
            radius = pool.empty(V, wp.float32)
            radius.fill_(np.float32(tmax))
            chunk = _plan.Bounds(b.lo, b.hi, tmax, tmax, b.lmax, b.lmean)
            if soft:
                plans = [_plan.plan(x, radius, f.mid, chunk, concrete, tmax, t, splits=splits, orders=self._orders,
                                    pool=pool)]
            else:
                plans = _plan.ball_plans(x, radius, f.mid, f.length, chunk, concrete, t, splits=splits,
                                         orders=self._orders, pool=pool)
            groups = plans[0][1]
            rows = 16 * len(plans) * groups.splits
            part_num = pool.empty((rows, groups.padded), wp.float32)
            part_den = pool.empty((rows, groups.padded), wp.float32)
            if not soft:  # every traversal reads the edges in one sorted order (ball_plans)
                seg_m, seg_h, val = (pool.empty(E, wp.vec4) for _ in range(3))
                wp.launch(_g.pack_ball_sources, dim=E, inputs=[plans[0][0].order, x, f.edges, f.angle, f.normal],
                          outputs=[seg_m, seg_h, val], device=device, record_tape=False)
            for i, (cells, grp) in enumerate(plans):
                if soft:
                    pos = pool.empty(E, wp.vec4)
                    val = pool.empty(E, wp.vec4)
                    wp.launch(_g.pack_soft_sources, dim=E, inputs=[cells.order, f.mid, f.length, f.angle, f.normal],
                              outputs=[pos, val], device=device, record_tape=False)
                    wp.launch(_s.soft_cells_multiscale, dim=grp.dim,
                              inputs=[x, taus_wp, offset, k, *grp.args(cells), pos, val],
                              outputs=[part_num, part_den], device=device)
                else:
                    wp.launch(_s.ball_cells_multiscale, dim=grp.dim,
                              inputs=[x, taus_wp, offset, k, *grp.args(cells), seg_m, seg_h, val, grp.splits,
                                      i * grp.splits],
                              outputs=[part_num, part_den], device=device)
            wp.launch(_s.reduce_multiscale, dim=(min(16, S - offset), V),
                      inputs=[groups.order, part_num, part_den, offset], outputs=[H], device=device)

    # --- which strategy "auto" takes ----------------------------------------------------------------------------

    def choose_strategy(self, tau, *, variant: str = "soft", positions: wp.array | None = None) -> str:
        """The traversal ``strategy="auto"`` takes for VNC-soft ("soft") or VNC-hard / Eq. (1) ("hard") at ``tau``."""
        if variant not in ("soft", "hard"):
            raise ValueError(f"variant must be 'soft' or 'hard', got {variant!r}")
        x = self.positions(positions)
        V, E = self.num_vertices, self.interior.shape[0]
        tau_arr = per_point(tau, V, self.device, "tau")
        stats = radius_stats(tau)
        if variant == "soft":
            b = self.host_bounds(x, stats) or _plan.bounds(x, tau_arr)
            return _plan.resolve("auto", self.device, b, b.rmean, V, E, self.tuning)
        f = self.fields(x)
        b = self.host_bounds(x, stats, lengths=True) or _plan.bounds(x, tau_arr, f.length)
        return _plan.resolve("auto", self.device, b, b.rmean + 0.5 * b.lmax, V, E, self.tuning)

