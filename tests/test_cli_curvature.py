"""`vnc-warp curvature` end to end on the CPU device."""

import numpy as np
import trimesh
from conftest import mesh_path

import vnc_warp as vw
from vnc_warp.cli import main


def test_curvature_cli_writes_ply_and_npz(tmp_path):
    """The command writes a coloured PLY and an .npz whose values equal the library call."""
    path = mesh_path("torus.obj")
    out = tmp_path / "sub" / "torus_vnc"
    assert main(["curvature", str(path), "--out", str(out), "--tau-edges", "3", "8", "--device", "cpu"]) == 0
    data = np.load(str(out) + ".npz")
    mesh = vw.load_mesh(path)
    assert data["H"].shape == (2, mesh.num_vertices)
    ref = vw.vnc_soft(mesh, 8 * mesh.mean_edge_length, device="cpu")[0].numpy()
    np.testing.assert_allclose(data["H"][1], ref, rtol=1e-5, atol=1e-6)
    ply = trimesh.load(str(out) + ".ply", process=False)
    colors = np.asarray(ply.visual.vertex_colors)
    assert len(ply.vertices) == mesh.num_vertices and colors[:, :3].std() > 0


def test_curvature_cli_bad_mesh_is_a_clear_error(tmp_path, capsys):
    """A missing mesh gives exit code 2 and a one-line error, not a traceback."""
    assert main(["curvature", str(tmp_path / "missing.obj"), "--out", str(tmp_path / "x")]) == 2
    assert "not found" in capsys.readouterr().err


def test_flow_cli_refuses_a_different_run_cleanly(tmp_path, capsys):
    """`vnc-warp flow` into a folder holding another run's manifest exits 2 with a one-line error."""
    from vnc_warp.shapes import random_shape

    mesh = tmp_path / "shape.obj"
    random_shape(1, subdivisions=2).save(mesh)
    out = tmp_path / "traj"
    assert main(["flow", str(mesh), "--stages", "1", "--out", str(out), "--device", "cpu", "--no-progress"]) == 0
    assert main(["flow", str(mesh), "--stages", "2", "--out", str(out), "--device", "cpu", "--no-progress"]) == 2
    assert "different run" in capsys.readouterr().err
