"""Float64 dense references of the paper's equations, written independently of the package.

Edge adjacency comes from trimesh (and, for the values of Eqs. (1)-(2), its dihedral angles, convexity and
segment/ball lengths); the sums are plain dense (V x E) NumPy/PyTorch, with no spatial pruning, no float32 and no
shared code with ``vnc_warp``. The differentiable references (:func:`dense_soft`, :func:`dense_hard`) are PyTorch
float64 for autograd.
"""

import numpy as np
import torch
import trimesh
from trimesh.curvature import line_ball_intersection


def _adjacency(vertices: np.ndarray, faces: np.ndarray):
    tm = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    return tm, tm.face_adjacency, tm.face_adjacency_edges, tm.face_adjacency_convex


def interior_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 4) int64 ``(a, b, c0, c1)`` per interior edge, from trimesh's face adjacency: face ``(a, b, c0)`` runs
    ``a -> b`` in its winding, the other face's corner is ``c1``."""
    f = np.asarray(faces, np.int64)
    tm = trimesh.Trimesh(np.zeros((f.max() + 1, 3)), f, process=False, validate=False)
    adj, edges = tm.face_adjacency, tm.face_adjacency_edges
    out = np.empty((len(adj), 4), np.int64)
    for i, ((f0, f1), (a, b)) in enumerate(zip(adj, edges)):
        t0, t1 = list(f[f0]), list(f[f1])
        if t0[(t0.index(a) + 1) % 3] != b:  # make a -> b the winding of face f0
            a, b = b, a
        out[i] = a, b, sum(t0) - a - b, sum(t1) - a - b
    return out


def edge_terms(verts: torch.Tensor, ev: np.ndarray):
    """Per interior edge ``(a, b, c0, c1)``: midpoint (E, 3), length (E,), signed dihedral angle (E,) and unit
    area-weighted normal (E, 3), differentiable in ``verts``. The angle is ``atan2`` of the faces' normals' cross
    product projected on the edge direction and their dot product: smooth through flat edges (``sign x |n0 x n1|``
    is not), positive on convex edges."""
    e = torch.as_tensor(ev)
    a, b, c0, c1 = (verts[e[:, i]] for i in range(4))
    d = b - a
    n0 = torch.cross(d, c0 - a, dim=1)
    n1 = torch.cross(a - b, c1 - b, dim=1)
    L = d.norm(dim=1)
    angle = torch.atan2((torch.cross(n0, n1, dim=1) * d).sum(1) / L, (n0 * n1).sum(1))
    ns = n0 + n1
    return 0.5 * (a + b), L, angle, ns / ns.norm(dim=1, keepdim=True)


def dense_soft(verts: torch.Tensor, faces: np.ndarray, tau, kappa: float = 6.0):
    """Eq. (3) over every interior edge within the cut-off ``tau``, float64, differentiable in ``verts`` (V, 3).

    Returns ``(H, n)``: (V,) curvature and (V, 3) unit normals (weights ``w L`` applied to the edges'
    area-weighted unit normals).
    """
    mid, L, angle, ue = edge_terms(verts, interior_edges(faces))
    tau = torch.as_tensor(np.broadcast_to(np.asarray(tau, np.float64), (verts.shape[0],)).copy())
    sigma = tau / kappa
    d2 = ((verts[:, None, :] - mid[None, :, :]) ** 2).sum(-1)
    w = torch.exp(-d2 / (2 * sigma[:, None] ** 2)) * L[None, :] * (d2 <= tau[:, None] ** 2)
    H = (w * angle[None, :]).sum(1) / (2 * w.sum(1))
    nsum = w @ ue
    return H, nsum / nsum.norm(dim=1, keepdim=True)


def dense_hard(verts: torch.Tensor, faces: np.ndarray, tau, kappa: float | None = 6.0):
    """Eq. (2) over every interior edge, float64, differentiable in ``verts`` (V, 3): balls of radius ``tau`` at the
    vertices, ``l`` the length of each edge inside a ball (the roots of ``|a + u (b - a) - x|^2 = r^2`` clipped to
    ``[0, 1]``, times the length), ``w`` the Gaussian of ``sigma = tau / kappa`` at the edge's midpoint (``kappa``
    None: w = 1). Returns ``(H, n)``."""
    ev = interior_edges(faces)
    mid, L, angle, ue = edge_terms(verts, ev)
    e = torch.as_tensor(ev)
    a, b = verts[e[:, 0]], verts[e[:, 1]]
    tau = torch.as_tensor(np.broadcast_to(np.asarray(tau, np.float64), (verts.shape[0],)).copy())
    d = (b - a)[None, :, :]
    f = a[None, :, :] - verts[:, None, :]
    dd = (d * d).sum(-1)
    fd = (f * d).sum(-1)
    disc = fd * fd - dd * ((f * f).sum(-1) - tau[:, None] ** 2)
    hit = disc > 0
    sq = torch.sqrt(torch.where(hit, disc, torch.ones_like(disc)))
    u1 = torch.clamp((-fd - sq) / dd, 0.0, 1.0)
    u2 = torch.clamp((-fd + sq) / dd, 0.0, 1.0)
    l = torch.where(hit, torch.clamp(u2 - u1, min=0.0), torch.zeros_like(disc)) * L[None, :]
    w = l
    if kappa is not None:
        d2 = ((verts[:, None, :] - mid[None, :, :]) ** 2).sum(-1)
        w = l * torch.exp(-d2 * kappa ** 2 / (2 * tau[:, None] ** 2))
    H = (w * angle[None, :]).sum(1) / (2 * w.sum(1))
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
