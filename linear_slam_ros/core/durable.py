"""Making what was written durable: fsync of a file or of a folder's entries."""

from __future__ import annotations

import os
from pathlib import Path


def fsync_path(path: Path) -> None:
    """Fsync ``path`` through a read-only descriptor: a file's bytes, or a folder's entries (a new or renamed file).

    Raises:
        OSError: the path cannot be opened or synced.
    """
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
