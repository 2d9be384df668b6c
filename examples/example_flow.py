# SPDX-License-Identifier: Apache-2.0
"""Example: VNC-Flow as a simulation.

Algorithm 1 of the paper written as a simulation loop from the library's public pieces: the input is
SDF-remeshed (topology regularization), its total VNC-AUC ``S_init`` sets an equal information budget per
stage (temporal balance), each stage assigns every vertex its adaptive scale (Eq. 6, spatial balance) and
then step() advances Eq. (5) one iteration at a time with :func:`vnc_warp.flow.flow_steps` until the
stage's budget is spent. The finished stage is recorded with its normalized time ``t`` (Eq. 7), remeshed,
and the next begins. render() draws each finished stage; the frames end up in one filmstrip PNG.

:func:`vnc_warp.flow.flow` runs the same algorithm in one call (with resumable output and baselines).

    python examples/example_flow.py --device cpu --stages 6
"""

import numpy as np
import warp as wp

import vnc_warp as vw
from vnc_warp.data import mesh_path
from vnc_warp.figures import auto_camera
from vnc_warp.flow import flow_steps, sphericity, total_complexity


class Example:
    """VNC-Flow of one mesh, one Eq. (5) iteration per step.

    Args:
        mesh: path of the input mesh (None: the bundled Spot).
        stages: number of stages N.
        faces: face count of every remeshed state.
        max_iters: iteration cap per stage.
        step_fraction: eta, the move of the 90th-percentile vertex per iteration, in mean edge lengths.
        frame_size: pixels per rendered frame; 0 renders nothing.
    """

    def __init__(self, mesh=None, stages=6, faces=3000, max_iters=100, step_fraction=0.25, frame_size=224):
        self.device = wp.get_device()
        self.faces = faces
        self.stages = stages
        self.max_iters = max_iters
        self.eta = step_fraction
        source = vw.load_mesh(mesh or mesh_path("spot"))
        self.mesh = vw.sdf_remesh(source, faces=faces, device=self.device)
        self.taus = vw.default_scales(self.mesh, 16)
        self.S_init = total_complexity(self.mesh, self.taus, device=self.device)
        self.phi_stage = self.S_init / stages
        self.meshes, self.t = [self.mesh], [1.0]
        self.stage = 0
        self.frame_size = frame_size
        self.frames, self.labels = [], []
        # the flow rounds the shape off, which can reach past the input's silhouette: leave room
        self.camera = auto_camera(self.mesh, margin=1.25) if frame_size else None
        self.finished = self.mesh  # the next render() draws it
        self.begin_stage()

    @property
    def done(self):
        return self.stage > self.stages

    def begin_stage(self):
        """Remesh the last state (from stage 2 on), assign adaptive scales (Eq. 6) and fix the step size."""
        self.stage += 1
        if self.done:
            return
        if self.stage > 1:
            self.mesh = vw.sdf_remesh(self.meshes[-1], faces=self.faces, device=self.device)
        curve = vw.scale_curve(self.mesh, self.taus, "soft", device=self.device)
        s = vw.vnc_auc(curve).numpy()
        self.tau = vw.adaptive_scale(curve, self.taus, 0.5 * float(s.mean()))
        self.x = wp.array(self.mesh.vertices, dtype=wp.vec3)
        # lambda: the 90th-percentile vertex moves eta mean edge lengths; capped for stability
        h, _ = vw.vnc_soft(self.mesh, self.tau, positions=self.x)
        h = h.numpy()
        q90 = float(np.quantile(np.abs(h - h.mean()), 0.9))
        edge = self.mesh.mean_edge_length
        self.lam = min(self.eta / q90 if q90 > 0 else 0.0, 6.0) * edge
        self.max_move = self.eta * edge
        self.target = self.S_init - self.stage * self.phi_stage
        self.iteration = 0

    def step(self):
        if self.done:
            return
        self.x = flow_steps(self.mesh, self.x, self.tau, 1, lam=self.lam, max_move=self.max_move)[-1]
        self.iteration += 1
        S = total_complexity(self.mesh, self.taus, positions=self.x)
        if S <= self.target or self.iteration >= self.max_iters:
            state = self.mesh.with_vertices(self.x.numpy())
            self.meshes.append(state)
            self.t.append(S / self.S_init)
            self.finished = state
            print(f"stage {self.stage}: {self.iteration:3d} iterations, t = {self.t[-1]:.3f}, "
                  f"sphericity {sphericity(state):.3f}")
            self.begin_stage()

    def render(self):
        if self.finished is None or not self.frame_size:
            return
        self.frames.append(vw.render_mesh(self.finished, camera=self.camera, width=self.frame_size,
                                          height=self.frame_size))
        self.labels.append(f"t = {self.t[len(self.frames) - 1]:.3f}")
        self.finished = None

    def save(self, path):
        vw.save_png(path, vw.montage(self.frames, labels=self.labels, label_height=30))


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--mesh", type=str, default=None, help="Input mesh (default: the bundled Spot).")
    parser.add_argument("--stages", type=int, default=6, help="Number of stages N.")
    parser.add_argument("--faces", type=int, default=3000, help="Face count of the remeshed states.")
    parser.add_argument("--max-iters", type=int, default=100, help="Iteration cap per stage.")
    parser.add_argument("--frame-size", type=int, default=224, help="Pixels per frame; 0 renders nothing.")
    parser.add_argument("--out", type=str, default="example_flow.png", help="Output PNG.")
    args = parser.parse_known_args()[0]

    with wp.ScopedDevice(args.device):
        example = Example(mesh=args.mesh, stages=args.stages, faces=args.faces, max_iters=args.max_iters,
                          frame_size=args.frame_size)
        example.render()
        while not example.done:
            example.step()
            example.render()
        if args.frame_size:
            example.save(args.out)
            print(f"wrote {args.out}")
