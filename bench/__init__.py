"""Benchmarks of vnc-warp. ``python -m bench.vnc --help`` runs the VNC operator benchmark."""
