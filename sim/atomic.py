"""Atomic file writes: a file that exists is complete.

Every writer here writes a temporary file in the target's folder (names starting with
``.tmp_``, which no reader globs for), flushes it, and renames it over the target, so a job
killed at any moment leaves either the old file, the new file, or a stray temporary file,
never a truncated target. Files are made world-readable (``mkstemp`` creates them private)
because caches and results are shared.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np


def write_atomic(path: str | os.PathLike, write: Callable[[IO[bytes]], None]) -> Path:
    """Call ``write(binary_file)`` on a temporary file, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp_", suffix=path.suffix)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_atomic(path, lambda fh: fh.write(text.encode()))


def savez(path: str | os.PathLike, compressed: bool = True, **arrays: np.ndarray) -> Path:
    save = np.savez_compressed if compressed else np.savez
    return write_atomic(path, lambda fh: save(fh, **arrays))
