"""Files that protect the user's work: output folders checked before anything is computed, atomic writes,
checksums, and a lock for read-modify-write of a file shared by several processes."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

__all__ = ["output_dir", "write_json", "write_bytes", "sha256_file", "locked"]


def output_dir(path: str | os.PathLike, *, what: str = "output folder") -> Path:
    """Create ``path`` (and its parents) and make sure files can be written into it, before any work is done.

    Args:
        path: the folder.
        what: how messages name it (e.g. ``"--out"``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        NotADirectoryError: ``path`` or one of its parents is a file.
        PermissionError: the folder cannot be created or written to (read-only, no permission).
        OSError: any other reason the system gives, with the folder named.
    """
    p = Path(path)
    blocker = next((q for q in [p, *p.parents] if q.exists() and not q.is_dir()), None)
    if blocker is not None:
        where = "is a file" if blocker == p else f"is under {blocker}, which is a file"
        raise NotADirectoryError(f"{what} {p} {where}, not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
        # os.access trusts permission bits (wrong for root, read-only mounts, immutable folders): write a probe
        fd, probe = tempfile.mkstemp(prefix=".vnc-warp-probe-", dir=p)
        os.close(fd)
        os.remove(probe)
    except PermissionError as exc:
        raise PermissionError(f"{what} {p} is not writable ({exc.strerror})") from None
    except OSError as exc:
        raise OSError(f"{what} {p} cannot be written to ({exc.strerror})") from None
    return p


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, then ``os.replace``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (a reader never sees half a file)."""
    write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode())


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def locked(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive lock on the file ``path`` (created) for a read-modify-write shared by several processes.

    The lock is ``flock`` on POSIX: the system releases it when its holder dies, so a killed process never blocks
    the next run. Where there is no ``fcntl`` (Windows) the block runs unlocked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - POSIX everywhere this runs
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
