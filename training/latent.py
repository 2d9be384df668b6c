"""Anatomy of the C-VAE latent space (Sec. 4.3, Fig. 11): how latents line up with the normalized time ``t``
(Eq. (7)), within each trajectory and across them.

The radial latent structure of Sec. 3.3 says that codes gather at the origin as ``t -> 0`` and reach the periphery
at ``t = 1``; Fig. 11b adds a shared direction along which every trajectory is ordered by t. :func:`analyze_latents`
measures both: the Pearson correlation of the latent norm with ``t`` (pooled over every sample, and within each
trajectory), and, for each of the first principal components of the mean-pooled latents, its correlation with ``t``
within every trajectory, with one sign for all (a direction shared by the trajectories); the best component is
the one whose weakest trajectory is ordered best. With umap-learn installed, UMAP of the max-pooled latents
(Fig. 11a) and the correlation of the distance from its centre with ``t``. Plots go through
:func:`vnc_warp.plot.scatter_plot`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vnc_warp.stats import pca, pearson

__all__ = ["analyze_latents", "latent_anatomy", "pca", "pearson", "trajectory_latents"]


def _numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _scatter(path: Path, xy: np.ndarray, t: np.ndarray, *, title: str, xlabel: str, ylabel: str) -> str:
    from vnc_warp.plot import scatter_plot

    order = np.argsort(t, kind="stable")  # high t drawn last, on top
    scatter_plot(xy[order, 0], xy[order, 1], c=t[order], clabel="t", title=title, xlabel=xlabel, ylabel=ylabel,
                 path=path, size=(640, 480))
    return str(path)


def _within(values: np.ndarray, t: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Pearson r of ``values`` with ``t`` inside every group of >= 3 samples."""
    out = {}
    for g in np.unique(labels):
        sel = labels == g
        if sel.sum() >= 3:
            out[str(g)] = pearson(values[sel], t[sel])
    return out


def analyze_latents(latents, t, *, out_dir: str | os.PathLike | None = None, seed: int = 0,
                    use_umap: bool = True, groups=None, prefix: str = "", title: str = "",
                    num_components: int = 5) -> dict:
    """Numbers and plots of the latent anatomy of Fig. 11.

    Args:
        latents: (N, M, C) latent sets (e.g. ``z_ctl`` with M tokens) or (N, C) latent vectors; NumPy or torch.
        t: (N,) normalized evolution time of each sample.
        out_dir: when given, writes ``<prefix>pca_mean_pooled.png`` (the best component against the other of
            the first two) and, with UMAP, ``<prefix>umap_max_pooled.png`` there.
        seed: UMAP random state.
        use_umap: run UMAP on the max-pooled latents when the ``umap`` package is importable.
        groups: (N,) labels (the trajectory of each sample): adds the within-trajectory numbers.
        prefix: file name prefix of the plots.
        title: prefix of the plot titles (e.g. the model).
        num_components: principal components examined.

    Returns:
        ``n``; ``norm_t_pearson`` (r of each latent's Frobenius norm with t, pooled: > 0 is the radial
        structure); ``explained_variance_ratio`` and ``pcs``: per component ``{"pc", "variance", "pooled_r",
        "within", "min_within"}`` with r signed so that the pooled r is >= 0 (``within`` by trajectory,
        ``min_within`` the weakest); ``best_pc``: the component with the largest ``min_within`` (with
        groups, else the largest ``|pooled_r|``); ``pc1_t_abs_pearson``; with ``groups`` also
        ``norm_t_within`` (by trajectory), ``norm_t_pearson_within`` (their mean), ``norm_t_min_within`` and
        ``pc1_t_pearson_within`` (mean over trajectories); ``umap`` (bool) and, with it,
        ``umap_radius_t_pearson``; ``plots`` ({name: path}).
    """
    z, t = _numpy(latents), _numpy(t).ravel()
    if z.ndim == 2:
        z = z[:, None, :]
    if z.ndim != 3 or z.shape[0] != t.shape[0] or z.shape[0] < 3:
        raise ValueError(f"analyze_latents: need (N, M, C) or (N, C) latents with N >= 3 and (N,) t, "
                         f"got {z.shape} and {t.shape}")
    labels = None
    if groups is not None:
        labels = np.asarray(groups).ravel()
        if labels.shape != t.shape:
            raise ValueError(f"analyze_latents: groups must be (N,) = {t.shape}, got {labels.shape}")
    mean_pooled, max_pooled = z.mean(axis=1), z.max(axis=1)
    k = min(num_components, *mean_pooled.shape)
    p = pca(mean_pooled, k)
    norms = np.linalg.norm(z.reshape(z.shape[0], -1), axis=1)
    pcs = []
    for i in range(k):
        r = pearson(p["scores"][:, i], t)
        sign = -1.0 if r < 0.0 else 1.0
        entry = {"pc": i + 1, "variance": float(p["explained_variance_ratio"][i]), "pooled_r": sign * r}
        if labels is not None:
            within = _within(sign * p["scores"][:, i], t, labels)
            entry["within"] = within
            entry["min_within"] = float(np.nanmin(list(within.values()))) if within else float("nan")
        pcs.append(entry)
    key = "min_within" if labels is not None else "pooled_r"
    best = max(pcs, key=lambda e: -np.inf if not np.isfinite(e[key]) else e[key])
    report = {
        "n": int(z.shape[0]),
        "norm_t_pearson": pearson(norms, t),
        "pc1_t_abs_pearson": abs(pearson(p["scores"][:, 0], t)),
        "explained_variance_ratio": [float(r) for r in p["explained_variance_ratio"]],
        "pcs": pcs,
        "best_pc": best,
        "umap": False,
        "plots": {},
    }
    if labels is not None:
        within = _within(norms, t, labels)
        report["norm_t_within"] = within
        values = list(within.values())
        report["norm_t_pearson_within"] = float(np.nanmean(values)) if values else float("nan")
        report["norm_t_min_within"] = float(np.nanmin(values)) if values else float("nan")
        pc1 = pcs[0].get("within", {})
        report["pc1_t_pearson_within"] = float(np.nanmean(list(pc1.values()))) if pc1 else float("nan")
    embedding = None
    if use_umap and z.shape[0] >= 4:
        try:
            import umap
        except ImportError:
            umap = None
        if umap is not None:
            reducer = umap.UMAP(n_components=2, n_neighbors=min(15, z.shape[0] - 1), random_state=seed)
            embedding = np.asarray(reducer.fit_transform(max_pooled))
            report["umap"] = True
            radius = np.linalg.norm(embedding - embedding.mean(axis=0), axis=1)
            report["umap_radius_t_pearson"] = pearson(radius, t)
    if out_dir is not None:
        out = Path(out_dir)
        head = f"{title}: " if title else ""
        b = best["pc"] - 1
        other = 1 if b == 0 and k > 1 else 0
        xy = np.stack([p["scores"][:, b], p["scores"][:, other] if k > 1 else np.zeros(len(t))], axis=1)
        report["plots"]["pca"] = _scatter(out / f"{prefix}pca_mean_pooled.png", xy, t,
                                          title=f"{head}PCA of mean-pooled latents", xlabel=f"PC{b + 1}",
                                          ylabel=f"PC{other + 1}")
        if embedding is not None:
            report["plots"]["umap"] = _scatter(out / f"{prefix}umap_max_pooled.png", embedding, t,
                                               title=f"{head}UMAP of max-pooled latents", xlabel="UMAP1",
                                               ylabel="UMAP2")
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
