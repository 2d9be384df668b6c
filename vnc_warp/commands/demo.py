"""``vnc-warp demo``: the paper's figures on a real mesh in one command.

On the bundled Spot (or ``--mesh``) the demo computes VNC across scales, runs a short VNC-Flow and, with
``--compare``, its fixed-scale and mean-curvature-flow baselines, then writes into ``--out``:

* the plots ``scale_stability`` (Fig. 6) and ``flow_auc`` (Fig. 8a) as PNG and PDF (matplotlib); the mesh
  renders ``curvature_scales.png`` (Fig. 5), ``adaptive_scales.png`` (Fig. 8b), ``filmstrip.png`` (Fig. 9a),
  ``comparison.png`` (Fig. 7); with ``--checkpoint`` of a trained C-VAE also ``decoded_trajectory.png``
  (Fig. 9b) and ``latent_space`` (Fig. 11, PNG and PDF);
* ``meshes/*.ply``: the input coloured by VNC at the scales of Fig. 5 and every flow stage coloured by VNC;
* ``summary.json``: settings, timings, the curvature statistics of Fig. 6, ``t``, sphericity, iterations
  and status per stage, the ``[width, height]`` of every PNG and the list of files written.

The default flow settings were chosen by measurement on a 2-core CPU (warm Warp kernel cache): Spot
remeshed to 4,000 faces (2,002 vertices), 8 stages, at most 100 iterations per stage, ``S`` evaluated every
2nd iteration, takes 27 s and ends at t = 0.08 with sphericity 0.89; the comparison flows at 1,500 faces,
4 stages, 60 iterations take 9 s together. The cost grows faster than linearly with the face count (the
last stages run at the largest scales): at the input's 5,856 faces the main flow alone takes 71 s.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np

HELP = "the paper's figures in one command: VNC across scales, a short VNC-Flow, PNGs, coloured PLYs, summary.json"

#: The vector copies of the plots (matplotlib writes a PDF beside each plot's PNG).
PLOTS = ("scale_stability.pdf", "flow_auc.pdf", "latent_space.pdf")

#: Fig. 7 rows: label -> FlowParams overrides of the comparison flows.
COMPARISON = {
    "(b) VNC-Flow\nadaptive scales": {},
    "(c) VNC-Flow\nfixed small scale": {"scale_mode": "small"},
    "(d) VNC-Flow\nfixed large scale": {"scale_mode": "large"},
    "(e) mean curv. flow\nexplicit": {"method": "mcf_explicit"},
    "(f) mean curv. flow\nimplicit": {"method": "mcf_implicit"},
}


def add_arguments(p) -> None:
    p.add_argument("--mesh", default=None, help="input mesh (any format trimesh reads); default: the bundled Spot")
    p.add_argument("--out", default="vnc_demo", help="output folder (created)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: CUDA when present")
    p.add_argument("--scales", type=int, default=16, help="scales of the VNC-Scale curves (Figs. 5, 6)")
    p.add_argument("--faces", type=int, default=4000, help="face count of the flow's remeshed states")
    p.add_argument("--stages", type=int, default=8, help="VNC-Flow stages N")
    p.add_argument("--max-iters", type=int, default=100, help="iteration cap per stage")
    p.add_argument("--eval-every", type=int, default=2, help="evaluate the total VNC-AUC every this many iterations")
    p.add_argument("--compare", action=argparse.BooleanOptionalAction, default=True,
                   help="also run the fixed-scale and mean-curvature-flow baselines (Fig. 7)")
    p.add_argument("--compare-faces", type=int, default=1500, help="face count of the comparison flows")
    p.add_argument("--compare-stages", type=int, default=4, help="stages of the comparison flows")
    p.add_argument("--compare-max-iters", type=int, default=60, help="iteration cap per stage of the comparison flows")
    p.add_argument("--frame-size", type=int, default=320, help="pixels per rendered frame")
    p.add_argument("--checkpoint", default=None,
                   help="a trained C-VAE (checkpoint file or run folder): also decode the input at the flow's t "
                        "(Fig. 9b) and plot its latents across t (Fig. 11)")
    p.add_argument("--resolution", type=int, default=64, help="marching-cubes grid of the decoded meshes")


def _vnc_colors(values: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    from vnc_warp.render import colormap

    return np.clip(np.rint(colormap(values, "coolwarm", *limits) * 255.0), 0, 255).astype(np.uint8)


class _Steps:
    """The demo's progress bar over its steps, and the wall time of each step."""

    def __init__(self, names: list[str], progress: bool):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=len(names), desc="vnc-warp demo", unit="step", disable=not progress, position=0)
        self.seconds: dict[str, float] = {}
        self._name, self._t0 = None, 0.0

    def start(self, name: str) -> None:
        self._name, self._t0 = name, time.perf_counter()
        self.bar.set_postfix_str(name)

    def done(self) -> None:
        self.seconds[self._name] = round(time.perf_counter() - self._t0, 3)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _cvae_figures(checkpoint, mesh, traj, out: Path, device, resolution: int, size: int, report: dict) -> dict:
    """Figs. 9b and 11 of a trained model: the input decoded at the flow's times, its latents across t."""
    import torch

    from vnc_warp import figures
    from vnc_warp.training.checkpoint import load_model
    from vnc_warp.training.inference import decode_mesh, surface_condition
    from vnc_warp.training.train import resolve_device

    tdev = resolve_device(str(device))
    model, config = load_model(checkpoint, device=tdev)
    surface, center, scale = surface_condition(mesh, num_points=config.data.num_surface)
    decoded = []
    for t in traj.t:
        try:
            decoded.append(decode_mesh(model, surface, float(t), resolution=resolution, center=center, scale=scale))
        except ValueError:  # no level set at this t (MeshError is a ValueError)
            decoded.append(None)
    images = {"decoded_trajectory.png": figures.decoded_trajectory(
        decoded, traj.t, out / "decoded_trajectory.png", reference=traj.meshes, reference_t=traj.t,
        frame_size=max(size * 5 // 8, 64), device=device)}
    report.update(checkpoint=str(checkpoint), model_kind=config.model.kind, t=[float(v) for v in traj.t],
                  decoded=[m is not None for m in decoded])
    if model.time_conditioned:
        times = np.linspace(0.0, 1.0, 21)
        batch = torch.as_tensor(surface, device=tdev).unsqueeze(0).expand(times.size, -1, -1)
        with torch.no_grad():
            z, _ = model.encode(batch, torch.as_tensor(times, dtype=torch.float32, device=tdev), sample=False)
        images["latent_space.png"] = figures.latent_space(z.float().cpu().numpy(), times, out / "latent_space.png")
    else:
        report["note"] = "the model is not time-conditioned: no latent-space figure"
    return images


def run(args) -> int:
    import vnc_warp as vw
    from vnc_warp import figures
    from vnc_warp._device import get_device
    from vnc_warp._files import output_dir
    from vnc_warp.data import mesh_path
    from vnc_warp.flow import flow, sphericity

    for name in ("scales", "faces", "stages", "max_iters", "eval_every", "compare_faces", "compare_stages",
                 "compare_max_iters", "frame_size", "resolution"):
        if getattr(args, name) < (2 if name == "scales" else 1):
            raise ValueError(f"--{name.replace('_', '-')} must be >= {2 if name == 'scales' else 1}")
    t_start = time.perf_counter()
    out = Path(args.out)
    output_dir(out / "meshes", what="--out")
    device = get_device(args.device)
    src = str(args.mesh or mesh_path("spot"))
    mesh = vw.load_mesh(src)
    progress = not args.no_progress
    files: list[Path] = []
    images: dict[str, np.ndarray] = {}
    notes: list[str] = []
    steps = _Steps(["curvature", "flow", "flow figures"] + (["comparison"] if args.compare else [])
                   + (["C-VAE"] if args.checkpoint else []), progress)
    size = args.frame_size

    # Figs. 5 and 6: VNC-soft, VNC-hard and the Eq. (1) baseline at every scale of the input as shipped
    steps.start("curvature")
    taus = vw.default_scales(mesh, args.scales)
    soft = vw.scale_curve(mesh, taus, "soft", device=device).H.numpy()
    hard = vw.scale_curve(mesh, taus, "hard", device=device).H.numpy()
    base = np.stack([vw.integrated_mean_curvature(mesh, float(tau), device=device).numpy() for tau in taus])
    shown = figures._evenly(taus.size, 5)
    limits = figures._shared_limits([soft[i] for i in shown], centre=True)
    images["curvature_scales.png"] = figures.curvature_scales(mesh, soft, taus, out / "curvature_scales.png",
                                                              limits=limits, frame_size=size, device=device)
    images["scale_stability.png"] = figures.scale_stability(
        taus, {"VNC-soft (Eq. 3)": soft, "VNC-hard (Eq. 2)": hard}, {"baseline (Eq. 1)": base},
        out / "scale_stability.png", edge_length=mesh.mean_edge_length)
    for i in shown:
        p = out / "meshes" / f"input_vnc_scale{i:02d}.ply"
        mesh.save(p, vertex_colors=_vnc_colors(soft[i], limits))
        files.append(p)
    steps.done()

    # VNC-Flow (Algorithm 1)
    steps.start("flow")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj = flow(mesh, args.stages, args.faces, device, progress=progress, max_iters=args.max_iters,
                    eval_every=args.eval_every)
    notes += [str(w.message) for w in caught]
    steps.done()

    # Figs. 8a, 8b, 9a and the coloured stages
    steps.start("flow figures")
    params = traj.info["params"]
    flow_taus = np.asarray(traj.info["taus"])
    images["flow_auc.png"] = figures.flow_auc(traj, out / "flow_auc.png")
    picked = figures._evenly(len(traj.meshes) - 1, 4) if len(traj.meshes) > 2 else [0]
    maps, curves = [], {}
    for i, m in enumerate(traj.meshes):
        curves[i] = vw.scale_curve(m, flow_taus, "soft", kappa=params["kappa"], device=device)
    for i in picked:
        s = vw.vnc_auc(curves[i]).numpy()
        maps.append(vw.adaptive_scale(curves[i], flow_taus, params["phi_fraction"] * float(s.mean())).numpy())
    images["adaptive_scales.png"] = figures.adaptive_scales(
        [traj.meshes[i] for i in picked], maps, out / "adaptive_scales.png",
        labels=[f"stage {i}, t = {traj.t[i]:.3f}" for i in picked],
        limits=(float(flow_taus[0]), float(flow_taus[-1])), frame_size=size, device=device)
    images["filmstrip.png"] = figures.filmstrip(traj.meshes, traj.t, out / "filmstrip.png",
                                                frame_size=max(size * 4 // 5, 64), device=device)
    mid = flow_taus.size // 2
    stage_h = [curves[i].H.numpy()[mid] for i in range(len(traj.meshes))]
    stage_limits = figures._shared_limits(stage_h[:1], centre=True)
    for i, m in enumerate(traj.meshes):
        p = out / "meshes" / f"stage_{i:03d}.ply"
        m.save(p, vertex_colors=_vnc_colors(stage_h[i], stage_limits))
        files.append(p)
    steps.done()

    comparison = {}
    if args.compare:
        steps.start("comparison")
        rows, times, status = {}, {}, {}
        for label, overrides in COMPARISON.items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                run_ = flow(mesh, args.compare_stages, args.compare_faces, device, progress=progress,
                            max_iters=args.compare_max_iters, eval_every=args.eval_every, **overrides)
            rows[label], times[label] = run_.meshes, run_.t
            status[label] = [r["status"] for r in run_.records]
            comparison[label.replace("\n", " ")] = {
                "params": overrides, "t": [float(v) for v in run_.t],
                "status": [r["status"] for r in run_.records], "final_sphericity": run_.records[-1]["sphericity"]}
        images["comparison.png"] = figures.flow_comparison(rows, times, out / "comparison.png", status=status,
                                                           frame_size=max(size * 5 // 8, 64), device=device)
        steps.done()
    cvae = {}
    if args.checkpoint:
        steps.start("C-VAE")
        images.update(_cvae_figures(args.checkpoint, mesh, traj, out, device, args.resolution, size, cvae))
        steps.done()
    steps.close()

    total = time.perf_counter() - t_start
    summary = {
        "mesh": src, "name": mesh.name, "vertices": mesh.num_vertices, "faces": mesh.num_faces, "device": str(device),
        "settings": {k: v for k, v in vars(args).items() if not k.startswith("_") and k not in ("mesh", "out")},
        "seconds": {**steps.seconds, "total": round(total, 3)},
        "curvature": {
            "taus": taus.tolist(), "mean_edge_length": mesh.mean_edge_length,
            "vnc_soft": {"mean": soft.mean(1).tolist(), "var": soft.var(1).tolist()},
            "vnc_hard": {"mean": hard.mean(1).tolist(), "var": hard.var(1).tolist()},
            "baseline_eq1": {"mean": base.mean(1).tolist(), "var": base.var(1).tolist()},
        },
        "flow": {
            "t": [float(v) for v in traj.t], "sphericity": [r["sphericity"] for r in traj.records],
            "iterations": [r["iterations"] for r in traj.records], "status": [r["status"] for r in traj.records],
            "vertices": [r["vertices"] for r in traj.records], "seconds": [r["seconds"] for r in traj.records],
            "input_sphericity": sphericity(mesh), "S_init": traj.info["S_init"],
        },
        "comparison": comparison,
        "cvae": cvae,
        "notes": notes,
        "images": {name: [int(img.shape[1]), int(img.shape[0])] for name, img in images.items()},
        "files": list(images) + [n[:-4] + ".pdf" for n in images if n[:-4] + ".pdf" in PLOTS]
                 + [os.path.relpath(f, out) for f in files] + ["summary.json"],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"vnc-warp demo: {mesh.name} on {device}, {total:.1f} s; t = "
          + ", ".join(f"{v:.3f}" for v in traj.t) + f"; wrote {len(summary['files'])} files to {out}:")
    for f in summary["files"]:
        if f.endswith((".png", ".pdf")) or f == "summary.json":
            print(f"  {out / f}")
    return 0
