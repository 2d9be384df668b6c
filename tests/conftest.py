"""Shared fixtures: the devices present (CPU always, CUDA when there is one) and the test meshes.

The meshes the suite needs ship with the repository (``tests/data``, credits in ``tests/data/CREDITS.md``; the
package's bundled Spot as ``spot_lowres.obj``) or are generated here. The real meshes of ``../shared/data/meshes``
only add coverage: :func:`mesh_cases` appends them as extra parameters, marked ``shared``, when that folder sits
beside the checkout, so a clone without it runs the same tests with fewer parameters and skips nothing
(``python -m pytest -m shared`` runs the extra ones alone).
"""

import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp

import vnc_warp._device  # noqa: F401  (quiet Warp, initialised before anything else asks about CUDA)
from vnc_warp.data import mesh_path as _package_mesh

DATA = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])

#: Meshes shipped with the repository, by the name the tests use.
BUNDLED = {
    "spot_lowres.obj": _package_mesh("spot"),
    **{p.name: p for p in sorted(DATA.glob("*.obj"))},
}


@pytest.fixture(params=DEVICES)
def device(request):
    """Every test that takes ``device`` runs once per device present."""
    return request.param


def mesh_path(name: str) -> Path:
    """Path of a test mesh: a bundled one (``BUNDLED``), else one of ../shared/data/meshes (for parameters made
    by :func:`mesh_cases` only)."""
    if name in BUNDLED:
        return BUNDLED[name]
    p = SHARED / name
    if not p.exists():
        raise FileNotFoundError(f"{name} is neither bundled ({', '.join(BUNDLED)}) nor in {SHARED}")
    return p


def mesh_cases(*bundled, shared=()) -> list:
    """Test parameters: every ``bundled`` case, then the ``shared`` cases whose mesh is in ../shared/data/meshes
    (marked ``shared``). A case is a mesh name or a tuple whose first item is one."""
    def name(case):
        return case[0] if isinstance(case, tuple) else case

    missing = [name(c) for c in bundled if name(c) not in BUNDLED and name(c) not in GENERATED]
    if missing:
        raise ValueError(f"not bundled: {missing}")
    cases = [pytest.param(*(c if isinstance(c, tuple) else (c,)), id=_case_id(c)) for c in bundled]
    cases += [pytest.param(*(c if isinstance(c, tuple) else (c,)), id=f"shared-{_case_id(c)}",
                           marks=pytest.mark.shared)
              for c in shared if (SHARED / name(c)).exists()]
    return cases


def _case_id(case) -> str:
    return "-".join(str(v) for v in case) if isinstance(case, tuple) else str(case)


def open_scan():
    """A closed mesh made open, as a raw scan is: penguin.obj with its base cut away (every face with a vertex in
    the lowest 12 % of its height) and a window in its side; a ``trimesh.Trimesh`` with two boundary loops."""
    import trimesh

    tm = trimesh.load(BUNDLED["penguin.obj"], process=False, force="mesh", maintain_order=True)
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    lo, hi = v[:, 1].min(), v[:, 1].max()
    low = (v[f][:, :, 1] < lo + 0.12 * (hi - lo)).any(axis=1)
    centre = v.mean(0) + np.array([0.0, 0.1 * (hi - lo), 0.0])
    side = np.linalg.norm(v[f].mean(1) - (centre + np.array([0.0, 0.0, np.ptp(v[:, 2]) / 2])), axis=1) < 0.12 * (hi - lo)
    return trimesh.Trimesh(v, f[~(low | side)], process=False)


def rescaled(name: str, diagonal: float):
    """A bundled mesh scaled (about its centre, then moved off the origin) to a bounding-box diagonal of
    ``diagonal`` units: nothing may assume unit size or a position near the origin."""
    import vnc_warp as vw

    m = vw.load_mesh(mesh_path(name))
    v = m.vertices.astype(np.float64)
    c = 0.5 * (v.min(0) + v.max(0))
    return vw.from_arrays((v - c) * (diagonal / m.bbox_diagonal) + 3.0 * diagonal, m.faces,
                          name=f"{name} x{diagonal:g}")


#: Generated cases :func:`load_case` knows, by name.
GENERATED = {"open-penguin": "penguin.obj with holes (open_scan)", "penguin@0.15": "penguin.obj at 0.15 units",
             "goathead@500": "goathead.obj at 500 units"}


def load_case(name: str):
    """The Mesh of a case name: bundled, generated (``GENERATED``) or shared."""
    import vnc_warp as vw

    if name == "open-penguin":
        return vw.load_mesh(open_scan(), name=name)
    if "@" in name:
        base, diagonal = name.split("@")
        return rescaled(base + ".obj", float(diagonal))
    return vw.load_mesh(mesh_path(name))


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny models run fastest on one torch thread; more threads oversubscribe a shared small CPU. Modules opt in
    with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def free_port():
    """A callable giving a TCP port free on this machine now, for torchrun's rendezvous: a fixed port failed when
    two suites ran at once."""

    def pick() -> int:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    return pick
