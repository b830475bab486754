"""Atomic file writes: a reader sees the old file or the whole new one, never half of one."""
from __future__ import annotations

import os
from pathlib import Path


def write_atomic(path: Path, write) -> None:
    """Write `path` by `write(tmp)` into a temporary file beside it, then rename it into place: readers
    never see half a file, and the temporary file never outlives a failed write (a full disk)."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
