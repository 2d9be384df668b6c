"""Shared fixtures: the devices present (CPU always, CUDA when there is one) and the real meshes."""

from pathlib import Path

import pytest
import torch
import warp as wp

import vnc_warp._device  # noqa: F401  (quiet Warp before anything initialises it)

MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    """Every test that takes ``device`` runs once per device present."""
    return request.param


def real_mesh_path(name: str) -> Path:
    """Path of a real mesh in ../shared/data/meshes; skips the test when the folder is absent."""
    p = MESHES / name
    if not p.exists():
        pytest.skip(f"real mesh {name} not available at {MESHES}")
    return p


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny models run fastest on one torch thread; more threads oversubscribe a shared small CPU. Modules opt in
    with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
