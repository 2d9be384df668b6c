"""Anatomy of the C-VAE latent space (Sec. 4.3, Fig. 11): PCA of mean-pooled latents, UMAP of
max-pooled latents, and how both line up with the normalized evolution time ``t`` (Eq. (7)).

The radial latent structure of Sec. 3.3 predicts that latent codes shrink toward the origin as
``t -> 0``: :func:`analyze_latents` reports the Pearson correlation of the latent norm with ``t`` and
``|r|`` of the first principal component of the mean-pooled latents with ``t`` (the "parallel
structure" of Fig. 11b; the sign of a principal axis is arbitrary), and writes scatter plots coloured
by ``t`` (matplotlib when importable, else Pillow, so a plot is always produced).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["analyze_latents", "latent_anatomy", "pca", "pearson", "scatter_png", "trajectory_latents"]

# viridis at 0, 1/4, 1/2, 3/4, 1 (RGB), for the Pillow fallback
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)


def _numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def pearson(x, y) -> float:
    """Pearson correlation coefficient of two (N,) sequences; NaN when either is constant."""
    x, y = _numpy(x).ravel(), _numpy(y).ravel()
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"pearson: need two equal-length sequences of >= 2 values, got {x.shape} and {y.shape}")
    x, y = x - x.mean(), y - y.mean()
    den = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / den) if den > 0.0 else float("nan")


def pca(x, k: int = 2) -> dict[str, np.ndarray]:
    """Principal component analysis by SVD of the centred data.

    Args:
        x: (N, C) samples.
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


def _viridis(values: np.ndarray) -> np.ndarray:
    pos = np.clip(values, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    lo = np.minimum(pos.astype(int), len(_VIRIDIS) - 2)
    w = (pos - lo)[:, None]
    return ((1.0 - w) * _VIRIDIS[lo] + w * _VIRIDIS[lo + 1]).round().astype(np.uint8)


def _scatter_pillow(path: Path, xy: np.ndarray, values: np.ndarray, title: str, xlabel: str, ylabel: str,
                    label: str, size: tuple[int, int]) -> None:
    from PIL import Image, ImageDraw

    w, h = size
    left, right, top, bottom = 60, w - 90, 30, h - 45
    img = Image.new("RGB", (w, h), "white")
    draw = ImageDraw.Draw(img)
    lo, hi = xy.min(0), xy.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    lo, span = lo - 0.05 * span, 1.1 * span
    px = left + (xy[:, 0] - lo[0]) / span[0] * (right - left)
    py = bottom - (xy[:, 1] - lo[1]) / span[1] * (bottom - top)
    vmin, vmax = float(values.min()), float(values.max())
    colors = _viridis((values - vmin) / (vmax - vmin) if vmax > vmin else np.full(values.shape, 0.5))
    draw.rectangle([left, top, right, bottom], outline="black")
    for frac in (0.0, 0.5, 1.0):
        x = left + frac * (right - left)
        y = bottom - frac * (bottom - top)
        draw.line([x, bottom, x, bottom + 4], fill="black")
        draw.text((x - 15, bottom + 6), f"{lo[0] + frac * span[0]:.3g}", fill="black")
        draw.line([left - 4, y, left, y], fill="black")
        draw.text((5, y - 5), f"{lo[1] + frac * span[1]:.3g}", fill="black")
    draw.text(((left + right) // 2 - 4 * len(xlabel), h - 20), xlabel, fill="black")
    draw.text((5, 8), f"{title}   (y: {ylabel})" if ylabel else title, fill="black")
    r = 3
    for i in np.argsort(values, kind="stable"):  # high t drawn last, on top
        draw.ellipse([px[i] - r, py[i] - r, px[i] + r, py[i] + r], fill=tuple(int(c) for c in colors[i]))
    bar = _viridis(np.linspace(1.0, 0.0, bottom - top))
    for k, c in enumerate(bar):
        draw.line([right + 20, top + k, right + 35, top + k], fill=tuple(int(v) for v in c))
    draw.text((right + 40, top - 5), f"{vmax:.3g}", fill="black")
    draw.text((right + 40, bottom - 5), f"{vmin:.3g}", fill="black")
    draw.text((right + 20, bottom + 6), label, fill="black")
    img.save(path)


def scatter_png(path: str | os.PathLike, xy, values, *, title: str = "", xlabel: str = "", ylabel: str = "",
                label: str = "t", size: tuple[int, int] = (640, 480), backend: str | None = None) -> str:
    """Write a 2D scatter plot coloured by ``values`` (viridis) to a PNG.

    Args:
        path: output ``.png`` path (parent folders created).
        xy: (N, 2) coordinates.
        values: (N,) colour values (e.g. ``t``).
        title, xlabel, ylabel, label: texts (``label`` names the colour bar).
        size: image size in pixels (width, height).
        backend: ``"matplotlib"``, ``"pillow"`` or None (matplotlib when importable, else Pillow).

    Returns:
        The backend used.
    """
    xy, values = _numpy(xy), _numpy(values).ravel()
    if xy.ndim != 2 or xy.shape[1] != 2 or values.shape[0] != xy.shape[0] or xy.shape[0] == 0:
        raise ValueError(f"scatter_png: need (N, 2) points and (N,) values, got {xy.shape} and {values.shape}")
    if backend not in (None, "matplotlib", "pillow"):
        raise ValueError(f"scatter_png: backend must be None, 'matplotlib' or 'pillow', got {backend!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if backend in (None, "matplotlib"):
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            if backend == "matplotlib":
                raise
        else:
            fig, ax = plt.subplots(figsize=(size[0] / 100, size[1] / 100), dpi=100)
            order = np.argsort(values, kind="stable")
            sc = ax.scatter(xy[order, 0], xy[order, 1], c=values[order], cmap="viridis", s=12)
            fig.colorbar(sc, ax=ax, label=label)
            ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
            fig.tight_layout()
            fig.savefig(path)
            plt.close(fig)
            return "matplotlib"
    _scatter_pillow(path, xy, values, title, xlabel, ylabel, label, size)
    return "pillow"


def analyze_latents(latents, t, *, out_dir: str | os.PathLike | None = None, seed: int = 0,
                    use_umap: bool = True, groups=None, prefix: str = "", title: str = "") -> dict:
    """Numbers and plots of the latent anatomy of Fig. 11.

    Args:
        latents: (N, M, C) latent sets (e.g. ``z_ctl`` with M = 2048 tokens) or (N, C) latent vectors;
            NumPy or torch.
        t: (N,) normalized evolution time of each sample.
        out_dir: when given, writes ``<prefix>pca_mean_pooled.png`` and (with UMAP)
            ``<prefix>umap_max_pooled.png`` there.
        seed: UMAP random state.
        use_umap: run UMAP on the max-pooled latents when the ``umap`` package is importable.
        groups: (N,) labels (e.g. the shape of each sample); adds the within-group correlations.
        prefix: file name prefix of the plots.
        title: prefix of the plot titles (e.g. the model).

    Returns:
        ``{"n", "norm_t_pearson" (r of the Frobenius norm of each latent with t, signed: > 0 is the radial
        structure), "pc1_t_abs_pearson" (|r| of PC1 of the mean-pooled latents with t),
        "explained_variance_ratio" ([PC1, PC2]), "umap" (bool), "plots" ({name: path}), "plot_backend"}``;
        with ``groups`` also ``"norm_t_pearson_within"`` and ``"pc1_t_pearson_within"``: the mean over
        groups of >= 3 samples of r within each group (PC1 of the pooled PCA, its sign fixed by the
        pooled correlation with t so that the groups are comparable), NaN when no group has 3 samples.
    """
    z, t = _numpy(latents), _numpy(t).ravel()
    if z.ndim == 2:
        z = z[:, None, :]
    if z.ndim != 3 or z.shape[0] != t.shape[0] or z.shape[0] < 3:
        raise ValueError(f"analyze_latents: need (N, M, C) or (N, C) latents with N >= 3 and (N,) t, "
                         f"got {z.shape} and {t.shape}")
    mean_pooled, max_pooled = z.mean(axis=1), z.max(axis=1)
    k = min(2, *mean_pooled.shape)
    p = pca(mean_pooled, k)
    scores = p["scores"] if k == 2 else np.concatenate([p["scores"], np.zeros_like(p["scores"])], axis=1)
    norms = np.linalg.norm(z.reshape(z.shape[0], -1), axis=1)
    pc1_r = pearson(scores[:, 0], t)
    report = {
        "n": int(z.shape[0]),
        "norm_t_pearson": pearson(norms, t),
        "pc1_t_abs_pearson": abs(pc1_r),
        "explained_variance_ratio": [float(r) for r in p["explained_variance_ratio"]],
        "umap": False,
        "plots": {},
        "plot_backend": None,
    }
    if groups is not None:
        labels = np.asarray(groups).ravel()
        if labels.shape != t.shape:
            raise ValueError(f"analyze_latents: groups must be (N,) = {t.shape}, got {labels.shape}")
        pc1 = scores[:, 0] * (-1.0 if pc1_r < 0.0 else 1.0)
        within_norm, within_pc1 = [], []
        for g in np.unique(labels):
            sel = labels == g
            if sel.sum() >= 3:
                within_norm.append(pearson(norms[sel], t[sel]))
                within_pc1.append(pearson(pc1[sel], t[sel]))
        report["norm_t_pearson_within"] = float(np.nanmean(within_norm)) if within_norm else float("nan")
        report["pc1_t_pearson_within"] = float(np.nanmean(within_pc1)) if within_pc1 else float("nan")
    embedding = None
    if use_umap and z.shape[0] >= 4:
        try:
            import umap
        except ImportError:
            umap = None
        if umap is not None:
            reducer = umap.UMAP(n_components=2, n_neighbors=min(15, z.shape[0] - 1), random_state=seed)
            embedding = reducer.fit_transform(max_pooled)
            report["umap"] = True
    if out_dir is not None:
        out = Path(out_dir)
        head = f"{title}: " if title else ""
        path = out / f"{prefix}pca_mean_pooled.png"
        report["plot_backend"] = scatter_png(path, scores, t, title=f"{head}PCA of mean-pooled latents",
                                             xlabel="PC1", ylabel="PC2")
        report["plots"]["pca"] = str(path)
        if embedding is not None:
            path = out / f"{prefix}umap_max_pooled.png"
            scatter_png(path, embedding, t, title=f"{head}UMAP of max-pooled latents", xlabel="UMAP1",
                        ylabel="UMAP2")
            report["plots"]["umap"] = str(path)
    return report


def trajectory_latents(model, traj_dirs, *, num_surface: int = 8192, seed: int = 0) -> dict:
    """Latents of every stage of VNC-Flow trajectories, the input of :func:`analyze_latents`.

    A time-conditioned model (C-VAE-I, C-VAE-II) encodes, as at inference, the trajectory's stage-0
    surface at each stage's normalized time t (z_ctl); a plain VAE encodes each stage's own surface.
    Every stage is normalized with its trajectory's stage-0 normalization, as in the training data.

    Args:
        model: a VecSet model in eval mode.
        traj_dirs: trajectory directories.
        num_surface: encoder surface samples per stage.
        seed: surface sampling seed.

    Returns:
        ``{"latents": (N, M, C) float32, "t": (N,) float64, "shape": [N names], "stage": [N indices]}``.
    """
    from .baseline import encode_surface
    from .data import normalization, read_trajectory
    from .inference import surface_condition

    latents, times, shapes, stages = [], [], [], []
    for traj_dir in traj_dirs:
        traj = read_trajectory(traj_dir)
        stage0 = traj.load_stage(0)
        norm = normalization(stage0)
        cond = surface_condition(stage0, num_points=num_surface, seed=seed, normalization=norm)[0]
        for pos, st in enumerate(traj.stages):
            if model.time_conditioned:
                z = encode_surface(model, cond, st.t)
            else:
                surface = surface_condition(traj.load_stage(pos), num_points=num_surface, seed=seed,
                                            normalization=norm)[0]
                z = encode_surface(model, surface)
            latents.append(z[0].cpu().numpy())
            times.append(st.t)
            shapes.append(traj.name)
            stages.append(st.index)
    if not latents:
        raise ValueError("trajectory_latents: no trajectories given")
    return {"latents": np.stack(latents).astype(np.float32), "t": np.asarray(times, dtype=np.float64),
            "shape": shapes, "stage": stages}


def latent_anatomy(model, traj_dirs, *, out_dir: str | os.PathLike | None = None, prefix: str = "",
                   title: str = "", num_surface: int = 8192, seed: int = 0, use_umap: bool = True,
                   figure: str | os.PathLike | None = None) -> dict:
    """Encode every stage of (held-out) trajectories and analyse the latents (Fig. 11).

    Args:
        model: a trained VecSet model in eval mode (C-VAE-I for Fig. 11; a plain VAE as the control).
        traj_dirs: trajectory directories.
        out_dir, prefix, title, use_umap: see :func:`analyze_latents`.
        num_surface, seed: see :func:`trajectory_latents`.
        figure: also draw Fig. 11 (:func:`vnc_warp.figures.latent_space`) to this PNG path.

    Returns:
        The :func:`analyze_latents` report (with within-trajectory correlations), plus ``"shapes"``
        (the trajectory names), ``"latent_shape"`` ([M, C]) and ``"encoding"``: ``"stage0_at_t"`` or
        ``"own_stage"``; with ``figure``, ``plots["fig11"]`` is its path.
    """
    data = trajectory_latents(model, traj_dirs, num_surface=num_surface, seed=seed)
    report = analyze_latents(data["latents"], data["t"], out_dir=out_dir, seed=seed, use_umap=use_umap,
                             groups=data["shape"], prefix=prefix, title=title)
    report.update(shapes=sorted(set(data["shape"])), latent_shape=list(data["latents"].shape[1:]),
                  encoding="stage0_at_t" if model.time_conditioned else "own_stage")
    if figure is not None:
        from vnc_warp.figures import latent_space

        latent_space(data["latents"], data["t"], figure, use_umap=use_umap, seed=seed,
                     title=f"Fig. 11  {title or 'C-VAE'} latents, every stage of {len(report['shapes'])} trajectories")
        report["plots"]["fig11"] = str(figure)
    return report
