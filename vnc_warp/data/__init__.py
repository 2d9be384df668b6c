"""Meshes shipped inside the package (credits in CREDITS.md)."""

from pathlib import Path

_HERE = Path(__file__).resolve().parent


def mesh_path(name: str = "spot") -> Path:
    """Path of a bundled mesh: ``"spot"`` (Keenan Crane's Spot, 2,930 vertices)."""
    p = _HERE / f"{name}.obj"
    if not p.exists():
        raise FileNotFoundError(f"no bundled mesh named {name!r}; available: {sorted(q.stem for q in _HERE.glob('*.obj'))}")
    return p
