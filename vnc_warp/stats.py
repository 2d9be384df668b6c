"""Small statistics shared by the figures and the latent-space analysis: Pearson correlation and PCA."""

from __future__ import annotations

import numpy as np

__all__ = ["pearson", "pca"]


def _numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def pearson(x, y) -> float:
    """Pearson correlation coefficient of two (N,) sequences (NumPy or torch); NaN when either is constant."""
    x, y = _numpy(x).ravel(), _numpy(y).ravel()
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"pearson: need two equal-length sequences of >= 2 values, got {x.shape} and {y.shape}")
    x, y = x - x.mean(), y - y.mean()
    den = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / den) if den > 0.0 else float("nan")


def pca(x, k: int = 2) -> dict[str, np.ndarray]:
    """Principal component analysis by SVD of the centred data.

    Args:
        x: (N, C) samples (NumPy or torch).
        k: number of components (<= min(N, C)).

    Returns:
        ``scores`` (N, k), ``components`` (k, C) unit rows, ``explained_variance_ratio`` (k,), ``mean`` (C,).
    """
    x = _numpy(x)
    if x.ndim != 2 or not 1 <= k <= min(x.shape):
        raise ValueError(f"pca: need (N, C) data and 1 <= k <= min(N, C), got shape {x.shape}, k={k}")
    mean = x.mean(axis=0)
    u, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    var = s**2
    total = var.sum()
    ratio = var[:k] / total if total > 0.0 else np.zeros(k)
    return {"scores": u[:, :k] * s[:k], "components": vt[:k], "explained_variance_ratio": ratio, "mean": mean}
