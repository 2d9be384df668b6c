"""Float64 dense references of the paper's equations, written independently of the package.

Edge adjacency, dihedral angles and convexity come from trimesh; the sums are plain dense
(V x E) NumPy/PyTorch, with no spatial pruning, no float32 and no shared code with ``vnc_warp``.
"""

import numpy as np
import torch
import trimesh
from trimesh.curvature import line_ball_intersection


def _adjacency(vertices: np.ndarray, faces: np.ndarray):
    tm = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    return tm, tm.face_adjacency, tm.face_adjacency_edges, tm.face_adjacency_convex


def dense_soft(verts: torch.Tensor, faces: np.ndarray, tau, kappa: float = 6.0):
    """Eq. (3) over every interior edge, float64, differentiable in ``verts`` (V, 3) float64.

    Returns ``(H, n)``: (V,) curvature and (V, 3) unit normals (weights ``w L`` applied to the edges'
    area-weighted unit normals).
    """
    _, adj, edges, convex = _adjacency(verts.detach().numpy(), faces)
    f = torch.as_tensor(np.asarray(faces, np.int64))
    fn = torch.cross(verts[f[:, 1]] - verts[f[:, 0]], verts[f[:, 2]] - verts[f[:, 0]], dim=1)
    adj = torch.as_tensor(np.array(adj))
    n0, n1 = fn[adj[:, 0]], fn[adj[:, 1]]
    u0 = n0 / n0.norm(dim=1, keepdim=True)
    u1 = n1 / n1.norm(dim=1, keepdim=True)
    alpha = torch.atan2(torch.cross(u0, u1, dim=1).norm(dim=1), (u0 * u1).sum(1))
    delta = torch.as_tensor(np.where(convex, 1.0, -1.0))
    e = torch.as_tensor(np.array(edges))
    a, b = verts[e[:, 0]], verts[e[:, 1]]
    mid = 0.5 * (a + b)
    L = (b - a).norm(dim=1)
    ue = (n0 + n1) / (n0 + n1).norm(dim=1, keepdim=True)
    tau = torch.as_tensor(np.broadcast_to(np.asarray(tau, np.float64), (verts.shape[0],)).copy())
    sigma = tau / kappa
    d2 = ((verts[:, None, :] - mid[None, :, :]) ** 2).sum(-1)
    w = torch.exp(-d2 / (2 * sigma[:, None] ** 2)) * L[None, :]
    H = (w * (alpha * delta)[None, :]).sum(1) / (2 * w.sum(1))
    nsum = w @ ue
    return H, nsum / nsum.norm(dim=1, keepdim=True)


def dense_ball_sums(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, radius, kappa):
    """Eqs. (1)-(2) densely: per point, ``sum alpha delta w l`` and ``sum w l`` over all interior edges.

    ``l`` is trimesh's exact segment/ball intersection length; ``w = exp(-|p - m|^2 / 2 sigma^2)``,
    ``sigma = radius / kappa`` (``kappa=None``: w = 1).
    """
    tm, _, edges, convex = _adjacency(vertices, faces)
    v = np.asarray(vertices, np.float64)
    angle = tm.face_adjacency_angles * np.where(convex, 1.0, -1.0)
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    mid = 0.5 * (a + b)
    radius = np.broadcast_to(np.asarray(radius, np.float64), (len(points),))
    num = np.zeros(len(points))
    den = np.zeros(len(points))
    for i, p in enumerate(np.asarray(points, np.float64)):
        l = line_ball_intersection(a, b, center=p, radius=radius[i])
        w = np.ones_like(l) if kappa is None else np.exp(-((p - mid) ** 2).sum(1) * kappa**2 / (2 * radius[i] ** 2))
        num[i] = (angle * w * l).sum()
        den[i] = (w * l).sum()
    return num, den


def dense_auc(H: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Eq. (4) at tau_max with the trapezoid rule, float64: H is (S, V)."""
    dev = np.abs(H - H.mean(axis=1, keepdims=True))
    return np.trapezoid(dev, taus, axis=0)


def dense_adaptive(H: np.ndarray, taus: np.ndarray, phi: float) -> np.ndarray:
    """Eq. (6) by brute force: the smallest tau (on a fine grid of each interval) where the running trapezoid
    integral of |H - mean| reaches phi; tau_max when it never does."""
    dev = np.abs(H - H.mean(axis=1, keepdims=True))
    out = np.full(H.shape[1], taus[-1])
    for k in range(H.shape[1]):
        acc = 0.0
        for s in range(1, len(taus)):
            inc = 0.5 * (dev[s - 1, k] + dev[s, k]) * (taus[s] - taus[s - 1])
            if inc > 0 and acc + inc >= phi:
                frac = np.linspace(0.0, 1.0, 100001)
                hit = frac[np.argmax(acc + frac * inc >= phi)]
                out[k] = taus[s - 1] + hit * (taus[s] - taus[s - 1])
                break
            acc += inc
    return out
