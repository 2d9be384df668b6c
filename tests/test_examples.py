"""Every script in examples/ runs on the CPU device with its small options, as Warp runs its own examples.

Each example runs in a fresh interpreter (as a user runs it) from a temporary folder; the checks use what
the examples print and write: the online VNC-AUC against the library's multi-scale curves, the flow's
normalized time falling stage by stage, the loss of the differentiable flow falling, and valid PNGs.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(script: str, tmp_path: Path, *options: str) -> str:
    """Run ``examples/<script>`` on the CPU with ``options``; its stdout (the run must succeed)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")  # tiny torch models: more threads only oversubscribe a small CPU
    # the checkout's package, whatever an installed one is (as pytest's own pythonpath does for the tests)
    env["PYTHONPATH"] = os.pathsep.join([str(EXAMPLES.parent)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                                                  if p])
    cmd = [sys.executable, str(EXAMPLES / script), "--device", "cpu", "--out", str(tmp_path / "out.png"), *options]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def _valid_png(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.format == "PNG"
        px = np.asarray(im.convert("RGB"))
    assert np.any(px < 250, axis=2).mean() > 0.02
    return px


def test_example_curvature(tmp_path):
    """Curvature across scales: the VNC-AUC accumulated one scale per step equals vnc_warp.vnc_auc of the
    library's multi-scale curves (a different kernel) to 0.01 % of its mean, and the figure is written."""
    out = _run("example_curvature.py", tmp_path, "--num-scales", "3", "--frame-size", "64")
    diff = float(re.search(r"max difference ([0-9.eE+-]+) %", out).group(1))
    assert diff < 0.01
    _valid_png(tmp_path / "out.png")


def test_example_flow(tmp_path):
    """The flow as a simulation: one line per stage, t strictly falling, sphericity rising toward 1."""
    out = _run("example_flow.py", tmp_path, "--stages", "2", "--faces", "600", "--max-iters", "10",
               "--frame-size", "64")
    stages = re.findall(r"stage (\d+): +\d+ iterations, t = ([0-9.]+), sphericity ([0-9.]+)", out)
    assert [int(s) for s, _, _ in stages] == [1, 2]
    t = [1.0] + [float(v) for _, v, _ in stages]
    assert all(b < a for a, b in zip(t, t[1:]))
    sph = [float(v) for _, _, v in stages]
    assert sph[1] > sph[0] and sph[1] <= 1.0
    _valid_png(tmp_path / "out.png")


def test_example_diff_flow(tmp_path):
    """The differentiable flow: gradients through K flow steps on a wp.Tape make the loss fall at least 5x
    in 20 Adam steps."""
    out = _run("example_diff_flow.py", tmp_path, "--train-iters", "20", "--subdivisions", "2", "--frame-size", "64")
    first, last = (float(v) for v in re.search(r"loss fell from ([0-9.eE+-]+) to ([0-9.eE+-]+)", out).groups())
    assert last < first / 5
    _valid_png(tmp_path / "out.png")


@pytest.mark.slow
def test_example_train_cvae(tmp_path):
    """The tiny C-VAE: flow, dataset, a few training steps, decoding and the latent figure run end to end with
    finite losses; both PNGs (Fig. 9b and Fig. 11) are written."""
    out = _run("example_train_cvae.py", tmp_path, "--num-frames", "1", "--steps-per-frame", "4", "--stages", "2",
               "--subdivisions", "2", "--resolution", "24")
    first, last = (float(v) for v in re.search(r"loss fell from ([0-9.eE+-]+) to ([0-9.eE+-]+)", out).groups())
    assert np.isfinite(first) and np.isfinite(last) and first > 0
    _valid_png(tmp_path / "out.png")
    _valid_png(tmp_path / "out_latents.png")
