"""The paper's formulation of VNC-soft (Eq. 3) in plain PyTorch: "global, dense matrix multiplications".

Written independently of ``vnc_warp`` (edge quantities included) as the baseline the benchmark compares
against. Distances come from one matrix product per block of vertices, ``|p|^2 - 2 p m^T + |m|^2`` (in
coordinates centred on the bounding box, which keeps float32 cancellation small); the block size keeps the
(block, E) weight matrix within a memory budget, so nothing of size V x E is ever held.
"""

from __future__ import annotations

import torch


def edge_tensors(vertices: torch.Tensor, interior: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Midpoints (E, 3), lengths (E,), signed dihedral angles (E,) and unit area-weighted normals (E, 3).

    ``interior`` is (E, 4) int64 ``(a, b, c0, c1)``: faces ``(a, b, c0)`` and ``(b, a, c1)``.
    """
    xa, xb = vertices[interior[:, 0]], vertices[interior[:, 1]]
    xc0, xc1 = vertices[interior[:, 2]], vertices[interior[:, 3]]
    e = xb - xa
    n0 = torch.cross(e, xc0 - xa, dim=1)
    n1 = torch.cross(xa - xb, xc1 - xb, dim=1)
    L = e.norm(dim=1)
    angle = torch.atan2((torch.cross(n0, n1, dim=1) * e).sum(1), (n0 * n1).sum(1) * L)
    ns = n0 + n1
    return 0.5 * (xa + xb), L, angle, ns / ns.norm(dim=1, keepdim=True).clamp_min(1e-30)


def block_rows(num_edges: int, device: torch.device, budget_bytes: int | None = None) -> int:
    """Vertices per block so that the block's float32 (rows, E) matrices (two live at once) fit the budget:
    a quarter of the free GPU memory (at most 4 GiB), or 256 MiB on the CPU."""
    if budget_bytes is None:
        if device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(device)
            budget_bytes = min(free // 4, 4 << 30)
        else:
            budget_bytes = 256 << 20
    return int(max(1, budget_bytes // (2 * 4 * max(num_edges, 1) + 1)))


@torch.no_grad()
def vnc_soft_dense(vertices: torch.Tensor, interior: torch.Tensor, tau: torch.Tensor, kappa: float = 6.0,
                   rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. (3) for every vertex against every interior edge, cut off at ``tau`` like ``vnc_warp.vnc_soft``.

    Args:
        vertices: (V, 3) float32.
        interior: (E, 4) int64 interior edges ``(a, b, c0, c1)``.
        tau: (V,) float32 scales.
        kappa: ``sigma = tau / kappa``.
        rows: vertices per block (default :func:`block_rows`).

    Returns:
        ``(H, n)``: (V,) and (V, 3) float32.
    """
    mid, L, angle, normal = edge_tensors(vertices, interior)
    centre = 0.5 * (vertices.max(0).values + vertices.min(0).values)
    p_all = vertices - centre
    m = mid - centre
    mT = m.t().contiguous()
    mm = (m * m).sum(1)
    feats = torch.cat([(L * angle)[:, None], L[:, None], L[:, None] * normal], dim=1)  # (E, 5)
    g_all = kappa * kappa / (2.0 * tau * tau)
    r2_all = tau * tau
    rows = rows or block_rows(mid.shape[0], vertices.device)
    out = torch.empty(vertices.shape[0], 5, dtype=vertices.dtype, device=vertices.device)
    for k0 in range(0, vertices.shape[0], rows):
        p = p_all[k0:k0 + rows]
        d2 = torch.addmm(mm.expand(p.shape[0], -1), p, mT, alpha=-2.0)
        d2.add_((p * p).sum(1, keepdim=True))
        outside = d2 > r2_all[k0:k0 + rows, None]
        d2.mul_(-g_all[k0:k0 + rows, None]).exp_().masked_fill_(outside, 0.0)
        torch.mm(d2, feats, out=out[k0:k0 + rows])
    den = out[:, 1]
    H = torch.where(den > 0, out[:, 0] / (2.0 * den), torch.zeros_like(den))
    nsum = out[:, 2:5]
    return H, nsum / nsum.norm(dim=1, keepdim=True).clamp_min(1e-30)

