"""Graph replay of an engine's repeated calls: the second identical call takes scratch of its own, the third captures,
every later one replays.

A call whose launches depend only on its key (operator, scales, kappa, strategy, and for positions given on the device
the plan they were made with) and on arrays the engine owns reads nothing back from the device. The first call with a
key runs as usual; the second runs with scratch that belongs to the table (allocated there, outside any capture, so
that no graph owns it); the third captures its launches into a graph (``wp.ScopedCapture``) over that scratch; that
call and every later one replay the graph (one launch), and the caller copies the results out. A call then costs the
device time and tens of microseconds of host time instead of about a millisecond of Python and launch overhead.

Each :class:`~vnc_warp._engine.Engine` holds one :class:`Replay` per stream, keeping at most ``max_graphs`` graphs
(least recently used first out). Calls made while the device is already capturing (a user's own graph) never replay.
Which device kinds replay is the engine's :class:`~vnc_warp.tuning.Tuning` (``replay``), by default the process-wide
setting of :func:`set_graph_replay`: CUDA only (on the CPU, kernel time dominates).
"""

from __future__ import annotations

import warnings
from collections import OrderedDict

import warp as wp

from ._plan import Pool

__all__ = ["set_graph_replay", "capture_failures", "Replay"]

# device kinds ("cuda", "cpu") whose repeated calls are replayed, for engines whose tuning does not say
_DEVICES = {"cuda"}

_SEEN = "seen"  # a key called once: the next call allocates the graph's scratch
_WARM = "warm"  # a key whose scratch exists: the next call captures
_PLAIN = "plain"  # a key whose capture failed: always run as usual

# (call kind, exception) of each failed capture in this process, the first few, for benchmarks and bug reports
_FAILURES: list = []


def set_graph_replay(*kinds: str) -> set:
    """The device kinds (``"cuda"``, ``"cpu"``) whose repeated operator calls are replayed from captured graphs
    (default: ``"cuda"``), for every engine whose :class:`~vnc_warp.tuning.Tuning` leaves ``replay`` unset; no
    argument turns replay off. Returns the previous set.

    >>> old = vnc_warp.set_graph_replay()          # every call launched as usual
    >>> vnc_warp.set_graph_replay(*old)            # back
    """
    global _DEVICES
    bad = set(kinds) - {"cuda", "cpu"}
    if bad:
        raise ValueError(f"device kinds are 'cuda' and 'cpu', got {sorted(bad)}")
    old, _DEVICES = _DEVICES, set(kinds)
    return old


def capture_failures() -> list[tuple[str, str]]:
    """``(kind, "ExceptionType: message")`` of the graph captures that failed in this process (the first 16): their
    calls run launch by launch, correct but with a launch's host overhead each (a warning says so once per kind)."""
    return list(_FAILURES)


def replayed_kinds(replay: tuple[str, ...] | None) -> set:
    """The device kinds that replay for a tuning's ``replay`` setting."""
    return set(_DEVICES) if replay is None else set(replay)


class Replay:
    """The graphs of one engine on one stream: key -> state, and the scratch the graphs share."""

    def __init__(self, device: wp.Device, max_graphs: int):
        self.device, self.max_graphs = device, max_graphs
        self.entries: OrderedDict = OrderedDict()
        self.store: dict = {}

    def graphs(self) -> list:
        """The keys whose graph is captured."""
        return [k for k, v in self.entries.items() if isinstance(v, tuple)]

    def captured(self, key: tuple) -> bool:
        """Whether the call ``key`` has a captured graph (:meth:`launch` replays it)."""
        return isinstance(self.entries.get(key), tuple)

    def launch(self, key: tuple) -> list:
        """Replay the captured graph of ``key`` (:meth:`captured`): its outputs, as :meth:`call` gives them."""
        graph, outs = self.entries[key]
        self.entries.move_to_end(key)
        wp.capture_launch(graph)
        return outs

    def drop(self, match) -> None:
        """Forget every key for which ``match(key)`` holds (their graphs too)."""
        for k in [k for k in self.entries if match(k)]:
            del self.entries[k]

    def call(self, key: tuple, kind: str, run, plain: Pool) -> tuple[list, bool]:
        """``(outputs, fresh)`` of ``run(pool, fresh)`` for the call ``key``, replayed from a graph when possible.

        ``run`` enqueues the call's launches (no read from the device) taking scratch from ``pool`` and returns its
        output arrays: new arrays when ``fresh``, else from ``pool`` too (the graph's outputs, which the caller copies
        out before the next call with the same key). ``plain``: the pool of a call run as usual.
        """
        state = self.entries.get(key)
        if state is None or state == _PLAIN:
            if state is None:
                self.entries[key] = _SEEN
                self._trim()
            return run(plain, True), True
        if state == _SEEN:
            # the scratch of the graph is allocated here, outside any capture: memory allocated while capturing would
            # belong to that graph, and the graphs of an engine share their scratch (a graph dropped later must not
            # take it)
            self.entries[key] = _WARM
            return run(Pool(self.device, kind, self.store, None), False), False
        if state == _WARM:
            pool = Pool(self.device, kind, self.store, None)
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                    outs = run(pool, False)
            except Exception as exc:  # a launch that cannot be captured: this key runs as usual from now on
                self.entries[key] = _PLAIN
                error = f"{type(exc).__name__}: {exc}"
                if not any(k == kind for k, _ in _FAILURES):
                    warnings.warn(f"vnc_warp: graph capture of a {kind!r} call on {self.device} failed ({error}); "
                                  "such calls run launch by launch from now on (correct, slower)", RuntimeWarning,
                                  stacklevel=2)
                if len(_FAILURES) < 16:
                    _FAILURES.append((kind, error))
                return run(plain, True), True
            state = (capture.graph, outs)
            self.entries[key] = state
            self.entries.move_to_end(key)
            self._trim()
        self.entries.move_to_end(key)
        graph, outs = state
        wp.capture_launch(graph)
        return outs, False

    def _trim(self) -> None:
        graphs = self.graphs()
        while len(graphs) > self.max_graphs:
            del self.entries[graphs.pop(0)]
        while len(self.entries) > 4 * self.max_graphs:
            self.entries.popitem(last=False)
