# SPDX-License-Identifier: Apache-2.0
"""Example: curvature across scales.

Sweeps the observation scale tau of VNC-soft (Eq. 3) from two mean edge lengths up to a quarter of the
bounding-box diagonal on the bundled Spot (or --mesh). Each step evaluates the curvature at the next scale
and accumulates the VNC-AUC of Eq. (4), ``s(v_k) = int |H(v_k, x) - mean_H(x)| dx``, on the fly with a
trapezoid kernel; render() draws the frame of that scale. The result is a PNG with the curvature at every
scale (Fig. 5) above the VNC-AUC map: complex regions (ears, horns, hooves) collect the most information.

The online VNC-AUC is checked against :func:`vnc_warp.vnc_auc` of the library's own VNC-Scale curves.

    python examples/example_curvature.py --device cpu --num-scales 8
"""

import numpy as np
import warp as wp

import vnc_warp as vw
from vnc_warp.figures import auto_camera
from vnc_warp.data import mesh_path


@wp.kernel(enable_backward=False)
def store_scale(h: wp.array(dtype=float), s: int, inv_count: float, H: wp.array2d(dtype=float),
                mean: wp.array(dtype=float)):
    """Row ``s`` of the scale curves: ``H[s, k] = h[k]`` and the global mean ``mean[s]`` (zeroed first)."""
    k = wp.tid()
    H[s, k] = h[k]
    wp.atomic_add(mean, s, h[k] * inv_count)


@wp.kernel(enable_backward=False)
def accumulate_auc(H: wp.array2d(dtype=float), mean: wp.array(dtype=float), s: int, dtau: float,
                   auc: wp.array(dtype=float)):
    """Eq. (4), one trapezoid between scales ``s - 1`` and ``s``: ``auc += dtau * (|d_{s-1}| + |d_s|) / 2``."""
    k = wp.tid()
    a = wp.abs(H[s - 1, k] - mean[s - 1])
    b = wp.abs(H[s, k] - mean[s])
    auc[k] = auc[k] + 0.5 * dtau * (a + b)


class Example:
    """VNC of one mesh at ``num_scales`` scales, one scale per step, with the VNC-AUC accumulated as it goes.

    Args:
        mesh: path of the input mesh (None: the bundled Spot).
        num_scales: scales of the sweep (>= 2).
        frame_size: pixels per rendered frame; 0 renders nothing.
    """

    def __init__(self, mesh=None, num_scales=8, frame_size=256):
        self.device = wp.get_device()
        self.mesh = vw.load_mesh(mesh or mesh_path("spot"))
        self.taus = vw.default_scales(self.mesh, num_scales)
        V = self.mesh.num_vertices
        self.positions = wp.array(self.mesh.vertices, dtype=wp.vec3)
        self.H = wp.zeros((num_scales, V), dtype=float)
        self.mean = wp.zeros(num_scales, dtype=float)
        self.auc = wp.zeros(V, dtype=float)
        self.scale = 0
        self.frame_size = frame_size
        self.frames, self.labels, self.limits = [], [], None
        self.camera = auto_camera(self.mesh) if frame_size else None

    @property
    def done(self):
        return self.scale >= len(self.taus)

    def step(self):
        s = self.scale
        h, _ = vw.vnc_soft(self.mesh, float(self.taus[s]), positions=self.positions)
        V = self.mesh.num_vertices
        wp.launch(store_scale, dim=V, inputs=[h, s, 1.0 / V], outputs=[self.H, self.mean])
        if s > 0:
            dtau = float(self.taus[s] - self.taus[s - 1])
            wp.launch(accumulate_auc, dim=V, inputs=[self.H, self.mean, s, dtau], outputs=[self.auc])
        self.scale += 1

    def render(self):
        if not self.frame_size:
            return
        h = self.H.numpy()[self.scale - 1]
        if self.limits is None:
            # the smallest scale varies most: its range, symmetric about its mean, holds every later frame
            half = float(np.quantile(np.abs(h - h.mean()), 0.98))
            self.limits = (float(h.mean()) - half, float(h.mean()) + half)
        self.frames.append(vw.render_mesh(self.mesh, scalars=h, vmin=self.limits[0], vmax=self.limits[1],
                                          camera=self.camera, width=self.frame_size, height=self.frame_size))
        tau = self.taus[self.scale - 1]
        self.labels.append(f"tau = {tau:.3g} ({tau / self.mesh.mean_edge_length:.1f} x edge)")

    def check(self):
        """Largest difference between the online VNC-AUC and the library's, relative to its mean."""
        curve = vw.scale_curve(self.mesh, self.taus, "soft", positions=self.positions)
        reference = vw.vnc_auc(curve).numpy()
        return float(np.abs(self.auc.numpy() - reference).max() / reference.mean())

    def save(self, path):
        """The frames with their colour bar, then the VNC-AUC map with its own, as one PNG."""
        auc = self.auc.numpy()
        width = min(self.frame_size * len(self.frames), 720)
        picture = vw.montage(
            [
                vw.montage(self.frames, labels=self.labels, cols=min(len(self.frames), 4), label_height=30),
                vw.colorbar("coolwarm", *self.limits, width=width, height=84),
                vw.render_mesh(self.mesh, scalars=auc, cmap="magma", camera=self.camera, width=self.frame_size,
                               height=self.frame_size),
                vw.colorbar("magma", float(auc.min()), float(auc.max()), width=width, height=84),
            ],
            labels=["", "VNC H (Eq. 3), dimensionless, one scale for all frames", "",
                    "VNC-AUC s (Eq. 4): information summed over all scales, mesh units"],
            cols=1, label_height=32,
        )
        vw.save_png(path, picture)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--mesh", type=str, default=None, help="Input mesh (default: the bundled Spot).")
    parser.add_argument("--num-scales", type=int, default=8, help="Scales of the sweep, one per step.")
    parser.add_argument("--frame-size", type=int, default=256, help="Pixels per frame; 0 renders nothing.")
    parser.add_argument("--out", type=str, default="example_curvature.png", help="Output PNG.")
    args = parser.parse_known_args()[0]

    with wp.ScopedDevice(args.device):
        example = Example(mesh=args.mesh, num_scales=args.num_scales, frame_size=args.frame_size)
        while not example.done:
            example.step()
            example.render()
        print(f"online VNC-AUC vs. vnc_warp.vnc_auc: max difference {100 * example.check():.3f} % of the mean")
        if args.frame_size:
            example.save(args.out)
            print(f"wrote {args.out}")
