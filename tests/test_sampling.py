"""Farthest-point sampling on the Warp kernel (vnc_warp.sampling, kernels/sampling.py) against the torch loop it
replaced, kept here as the oracle."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from vnc_warp.kernels import sampling as kernels
from vnc_warp.sampling import farthest_point_sample


def torch_loop_fps(points: torch.Tensor, num_samples: int, start: torch.Tensor) -> torch.Tensor:
    """The torch loop ``training.model.farthest_point_sample`` ran before the kernel (one small op per step)."""
    b, n, _ = points.shape
    pts = points.detach().float()
    rows = torch.arange(b, device=points.device)
    out = torch.empty(b, num_samples, dtype=torch.long, device=points.device)
    dist = torch.full((b, n), float("inf"), device=points.device)
    cur = start.to(device=points.device, dtype=torch.long)
    for i in range(num_samples):
        out[:, i] = cur
        d = (pts - pts[rows, cur].unsqueeze(1)).square().sum(-1)
        dist = torch.minimum(dist, d)
        cur = dist.argmax(-1)
    return out


@pytest.fixture
def tdevice(device):
    """Torch device for the Warp device fixture; skips CUDA when this torch build has none."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("torch has no CUDA")
    return torch.device(device)


def _clouds(seed: int) -> dict[str, torch.Tensor]:
    """Point clouds with and without exact ties, (B, N, 3) float32."""
    g = torch.Generator().manual_seed(seed)
    grid = torch.randint(-2, 3, (3, 150, 3), generator=g).float() * 0.25  # many equal distances, repeated points
    twice = torch.rand(2, 60, 3, generator=g).repeat(1, 2, 1)  # every point twice
    return {
        "uniform": torch.rand(3, 700, 3, generator=g) * 400.0 - 150.0,
        "normal_far": torch.randn(2, 500, 3, generator=g) * 0.05 + 1000.0,
        "grid": grid,
        "twice": twice,
        "one_point": torch.full((2, 9, 3), 0.5),
    }


@pytest.mark.parametrize("name", ["uniform", "normal_far", "grid", "twice", "one_point"])
def test_matches_torch_loop(tdevice, name):
    """The kernel's indices equal the torch loop's (run on the CPU, whose float32 sum of three squares is
    ``(x^2 + y^2) + z^2``) for every start and M in {1, 17, N}: random clouds far from the origin, grids full of
    equal distances, duplicated points (once all remaining distances are 0 both take the lowest index again),
    B > 1."""
    pts = _clouds(4)[name].to(tdevice)
    b, n, _ = pts.shape
    starts = [torch.zeros(b, dtype=torch.long), torch.arange(b) * 7 % n, torch.full((b,), n - 1)]
    for start in starts:
        for m in (1, min(17, n), n):
            got = farthest_point_sample(pts, m, start=start.to(tdevice))
            want = torch_loop_fps(pts.cpu(), m, start).to(tdevice)
            assert got.dtype == torch.int64 and got.device == pts.device and got.shape == (b, m)
            assert torch.equal(got, want), (name, start.tolist(), m)
            assert torch.equal(got[:, 0].cpu(), start)


def _squared_norms(p: torch.Tensor, order: str) -> torch.Tensor:
    """float32 squared norms of (..., 3) rows summed as ``(x^2 + y^2) + z^2`` ("xy_z"), ``(x^2 + z^2) + y^2``
    ("xz_y"), or with fused multiply-adds ``fma(z, z, fma(y, y, x^2))`` ("fma", each product exact in float64)."""
    if order == "fma":
        q = p.double()
        acc = (q[..., 0] * q[..., 0]).float()
        for k in (1, 2):
            acc = (q[..., k] * q[..., k] + acc.double()).float()
        return acc
    s = p.square()
    return (s[..., 0] + s[..., 1]) + s[..., 2] if order == "xy_z" else (s[..., 0] + s[..., 2]) + s[..., 1]


def test_distance_is_the_loops_float32_sum(tdevice):
    """Near-ties decided in the last bit: clouds ``[0, p, R p]`` (R a rotation, so |p| = |R p| up to rounding)
    whose second sample is 1 or 2 depending only on how the squared distances are rounded. The kernel picks as the
    loop does; summing in another order or with fused multiply-adds picks otherwise on some of them (checked here,
    so the test can tell)."""
    g = torch.Generator().manual_seed(11)
    p = torch.randn(256, 3, generator=g, dtype=torch.float64) * 37.0
    rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    pts = torch.stack([torch.zeros_like(p), p, p @ rot], dim=1).float()  # (256, 3, 3)
    want = torch_loop_fps(pts, 2, torch.zeros(256, dtype=torch.long))[:, 1]
    assert torch.equal(want, torch.where(_squared_norms(pts[:, 2], "xy_z") > _squared_norms(pts[:, 1], "xy_z"), 2, 1))
    for order in ("xz_y", "fma"):
        other = torch.where(_squared_norms(pts[:, 2], order) > _squared_norms(pts[:, 1], order), 2, 1)
        assert (other != want).sum() >= 10, order
    pts = pts.to(tdevice)
    assert torch.equal(farthest_point_sample(pts, 2)[:, 1].cpu(), want)


def test_start_defaults_and_random_start(tdevice):
    """No start: index 0; ``random_start``: the draw ``torch.randint(N, (B,))`` of the device's global RNG, as
    before; ``start`` overrides ``random_start``; other float dtypes and a strided view are read as float32; an empty
    batch and meta tensors (shapes only) give the output's shape."""
    g = torch.Generator().manual_seed(2)
    surface = torch.randn(3, 200, 6, generator=g, dtype=torch.float64).to(tdevice)
    xyz = surface[..., :3]  # not contiguous, float64: as the encoder passes its surface
    zero = torch.zeros(3, dtype=torch.long)
    assert torch.equal(farthest_point_sample(xyz, 30).cpu(), torch_loop_fps(xyz.cpu(), 30, zero))
    torch.manual_seed(5)
    drawn = torch.randint(200, (3,), device=tdevice)
    torch.manual_seed(5)
    got = farthest_point_sample(xyz, 30, random_start=True)
    assert torch.equal(got.cpu(), torch_loop_fps(xyz.cpu(), 30, drawn.cpu()))
    start = torch.tensor([4, 5, 6], dtype=torch.int32, device=tdevice)
    assert torch.equal(farthest_point_sample(xyz, 30, start=start, random_start=True)[:, 0].cpu(),
                       torch.tensor([4, 5, 6]))
    assert farthest_point_sample(xyz[:0], 30).shape == (0, 30)
    meta = farthest_point_sample(xyz.to("meta"), 30, start=start.to("meta"))
    assert meta.shape == (3, 30) and meta.dtype == torch.int64 and meta.device.type == "meta"


def test_full_sample_of_distinct_points_is_a_permutation():
    """M = N on distinct points picks every point once."""
    pts = torch.randn(2, 64, 3, generator=torch.Generator().manual_seed(0))
    idx = farthest_point_sample(pts, 64, random_start=True)
    assert all(sorted(row.tolist()) == list(range(64)) for row in idx)


@pytest.mark.parametrize("block_dim", [7, 64])
def test_kernel_blocks_of_many_threads(monkeypatch, block_dim):
    """The block-wide reduction on the CPU device with several threads per block (Warp's CPU blocks): threads own
    strided slices of unequal length (7 does not divide N) or none at all (64 > N); same indices as the loop."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    g = torch.Generator().manual_seed(block_dim)
    for pts in (torch.rand(3, 50, 3, generator=g), torch.randint(0, 3, (2, 40, 3), generator=g).float()):
        b, n, _ = pts.shape
        start = torch.arange(b) * 11 % n
        out = torch.empty(b, n, dtype=torch.long)
        dist = torch.empty(b, n)
        wp.launch_tiled(kernels.farthest_point_sample, dim=b, block_dim=block_dim, device="cpu",
                        inputs=[wp.from_torch(pts, dtype=wp.vec3), wp.from_torch(start), wp.from_torch(dist),
                                wp.from_torch(out)])
        assert torch.equal(out, torch_loop_fps(pts, n, start))


def test_bad_input_errors():
    """Bad shapes, sample counts and starts raise one-line ValueErrors naming the function and the argument."""
    pts = torch.randn(2, 25, 3)
    with pytest.raises(ValueError, match=r"farthest_point_sample: num_samples must be in \[1, 25\], got 26"):
        farthest_point_sample(pts, 26)
    with pytest.raises(ValueError, match="num_samples"):
        farthest_point_sample(pts, 0)
    with pytest.raises(ValueError, match=r"points must be \(B, N, 3\), got \(2, 25, 2\)"):
        farthest_point_sample(pts[..., :2], 4)
    with pytest.raises(ValueError, match="floating point"):
        farthest_point_sample(pts.long(), 4)
    with pytest.raises(ValueError, match=r"start must be \(2,\)"):
        farthest_point_sample(pts, 4, start=torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="start must hold integers"):
        farthest_point_sample(pts, 4, start=torch.zeros(2))
    with pytest.raises(ValueError, match=r"start must be in \[0, 25\), got \[0, 25\]"):
        farthest_point_sample(pts, 4, start=torch.tensor([0, 25]))
    with pytest.raises(ValueError, match=r"start must be in \[0, 25\)"):
        farthest_point_sample(pts, 4, start=torch.tensor([-1, 0]))
