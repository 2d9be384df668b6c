"""Graph replay of repeated operator calls: the second identical call captures, every later one replays.

A call of :func:`~vnc_warp.vnc_soft`, :func:`~vnc_warp.vnc_hard` or :func:`~vnc_warp.integrated_mean_curvature`
(at the vertices) on a mesh's own vertices, with scales given on the host, launches the same kernels with the same
arguments every time: nothing in it is read back from the device (the bounds come from the host, see
``operators._host_bounds``). Such a call is identified by a key (operator, scales, kappa, strategy). The first call
with a key runs as usual; the second runs with scratch that belongs to the mesh (allocated there, outside any
capture, so that no graph owns it); the third captures its launches into a graph (``wp.ScopedCapture``) over that
scratch; that call and every later one replay the graph (one launch) and copy the results into fresh arrays, so a call costs the device time and tens of microseconds of host time instead of about a millisecond of
Python and launch overhead.

The graphs live with the mesh (``mesh._cache``, dropped when ``mesh.vertices`` is replaced) and at most
:data:`MAX_GRAPHS` per mesh, device and stream are kept (least recently used first out). Calls made while the device
is already capturing (a user's own graph) never replay. :data:`DEVICES` says on which kinds of device replay is used:
CUDA only by default (on the CPU, kernel time dominates); the tests turn it on for the CPU device too, where Warp
records graphs as well.
"""

from __future__ import annotations

from collections import OrderedDict

import warp as wp

from ._pairs import Pool

__all__ = ["DEVICES", "MAX_GRAPHS", "call", "forget", "set_graph_replay"]

# device kinds ("cuda", "cpu") whose repeated calls are replayed
DEVICES = {"cuda"}
# captured graphs kept per mesh, device and stream
MAX_GRAPHS = 8

_SEEN = "seen"  # a key called once: the next call allocates the graph's scratch
_WARM = "warm"  # a key whose scratch exists: the next call captures
_PLAIN = "plain"  # a key whose capture failed: always run as usual


class _Graphs:
    """The replay table of one mesh, device and stream: key -> state, and the scratch the graphs share."""

    def __init__(self):
        self.entries: OrderedDict = OrderedDict()
        self.store: dict = {}


def _table(mesh, device: wp.Device) -> _Graphs:
    stream = device.stream.cuda_stream if device.is_cuda else 0
    return mesh._memo(("replays", device.alias, stream), _Graphs)


def set_graph_replay(*kinds: str) -> set:
    """The device kinds (``"cuda"``, ``"cpu"``) whose repeated operator calls are replayed from captured graphs
    (default: ``"cuda"``); no argument turns replay off. Returns the previous set. Graphs already captured stay with
    their meshes (:func:`forget` drops them).

    >>> old = vnc_warp.set_graph_replay()          # every call launched as usual
    >>> vnc_warp.set_graph_replay(*old)            # back
    """
    global DEVICES
    bad = set(kinds) - {"cuda", "cpu"}
    if bad:
        raise ValueError(f"device kinds are 'cuda' and 'cpu', got {sorted(bad)}")
    old, DEVICES = DEVICES, set(kinds)
    return old


def forget(mesh) -> None:
    """Drop every graph kept for ``mesh`` (e.g. after changing a module-level setting that the keys do not hold)."""
    for key in [k for k in mesh._cache if isinstance(k, tuple) and k and k[0] == "replays"]:
        del mesh._cache[key]


def enabled(device: wp.Device) -> bool:
    return ("cuda" if device.is_cuda else "cpu") in DEVICES and not device.is_capturing


def call(mesh, device: wp.Device, key: tuple, kind: str, run) -> list:
    """The outputs of ``run(pool, fresh)`` for the call ``key`` on ``mesh``, replayed from a graph when possible.

    ``run`` enqueues the call's launches (no read from the device) taking scratch from ``pool`` and returns its
    output arrays: new arrays when ``fresh``, else from ``pool`` too (the graph's outputs, copied out per replay).
    """
    if not enabled(device):
        return run(Pool(device, kind), True)
    table = _table(mesh, device)
    state = table.entries.get(key)
    if state is None or state == _PLAIN:
        if state is None:
            table.entries[key] = _SEEN
            _trim(table)
        return run(Pool(device, kind), True)
    if state == _SEEN:
        # the scratch of the graph is allocated here, outside any capture: memory allocated while capturing would
        # belong to that graph, and the graphs of a mesh share their scratch (a graph dropped later must not take it)
        table.entries[key] = _WARM
        outs = run(Pool(device, kind, store=table.store, limit=None), False)
        return [wp.clone(o) for o in outs]
    if state == _WARM:
        pool = Pool(device, kind, store=table.store, limit=None)
        try:
            with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                outs = run(pool, False)
        except Exception:  # a launch that cannot be captured: this key runs as usual from now on
            table.entries[key] = _PLAIN
            return run(Pool(device, kind), True)
        state = (capture.graph, outs)
        table.entries[key] = state
        table.entries.move_to_end(key)
        _trim(table)
    table.entries.move_to_end(key)
    graph, outs = state
    wp.capture_launch(graph)
    return [wp.clone(o) for o in outs]


def _trim(table: _Graphs) -> None:
    graphs = [k for k, v in table.entries.items() if isinstance(v, tuple)]
    while len(graphs) > MAX_GRAPHS:
        del table.entries[graphs.pop(0)]
    while len(table.entries) > 4 * MAX_GRAPHS:
        table.entries.popitem(last=False)
