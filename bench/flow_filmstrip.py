"""Before/after filmstrips of VNC-Flow trajectories: one row per trajectory folder, every k-th stage, one camera.

    python -m bench.flow_filmstrip BEFORE_DIR AFTER_DIR --labels "dd885f9" "this branch" --every 4 \\
        --title "human_man, 32 stages" --out docs/flow_human_man.png

Each folder is one written by ``vnc-warp flow`` or ``vw.flow(..., out_dir=...)``. Under each frame: the stage, its
``t`` (Eq. 7) and the 5th-percentile relative thickness recorded for it (recomputed when the manifest predates
that record). The camera is fitted to the first stage of the first folder, so every frame shares one scale.
"""

from __future__ import annotations

import argparse


def _banner(text: str, width: int):
    """A white strip ``width`` pixels wide with ``text`` centred on it."""
    import numpy as np

    from vnc_warp.render import montage

    return montage([np.full((2, width, 3), 255, np.uint8)], labels=[text], pad=0, label_height=30)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("folders", nargs="+", help="trajectory folders, one row each")
    p.add_argument("--labels", nargs="*", default=None, help="one row label per folder")
    p.add_argument("--every", type=int, default=4, help="show stages 0, k, 2k, ... and the last")
    p.add_argument("--frame", type=int, default=220, help="pixels per frame")
    p.add_argument("--title", default="VNC-Flow")
    p.add_argument("--device", default=None)
    p.add_argument("--out", required=True, help="PNG to write")
    args = p.parse_args(argv)

    from vnc_warp.figures import auto_camera
    from vnc_warp.flow import Trajectory, relative_thickness
    from vnc_warp.render import montage, render_mesh, save_png

    labels = args.labels or args.folders
    if len(labels) != len(args.folders):
        raise SystemExit(f"{len(args.folders)} folders but {len(labels)} labels")
    trajs = [Trajectory.load(f) for f in args.folders]
    camera = auto_camera(trajs[0].meshes[0])
    rows = []
    for label, traj in zip(labels, trajs):
        n = len(traj.meshes) - 1
        stages = sorted(set(range(0, n + 1, args.every)) | {n})
        frames, captions = [], []
        for i in stages:
            rec = traj.records[i]
            thick = rec.get("thickness")
            if thick is None:
                thick = relative_thickness(traj.meshes[i], device=args.device)
            frames.append(render_mesh(traj.meshes[i], camera=camera, width=args.frame, height=args.frame,
                                      device=args.device))
            captions.append(f"{i}: t {traj.t[i]:.3f}, thick {thick:.3f}")
        strip = montage(frames, labels=captions, pad=4)
        rows += [_banner(label, strip.shape[1]), strip]
    save_png(args.out, montage([_banner(args.title, rows[0].shape[1]), *rows], cols=1, pad=2))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
