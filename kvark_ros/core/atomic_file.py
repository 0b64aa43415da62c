"""Atomic file writes: a reader sees the old file or the new one, never half of one."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Callable


def write_atomically(path: Path, write: Callable[[Any], Any]) -> None:
    """Write ``path``: ``write(f)`` into a temp file beside it (binary), fsync, then os.replace."""
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        if os.path.exists(tmp_name):
            os.unlink(tmp_name)
        raise


def write_text_atomically(path: Path, text: str) -> None:
    """``Path.write_text``, atomically (UTF-8)."""
    write_atomically(path, lambda f: f.write(text.encode()))
