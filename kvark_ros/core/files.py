"""Files: atomic writes (a reader sees the old file or the new one, never half of one) and YAML
reads whose every failure is one user error naming the file, the problem and the fix."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import yaml


def umask_mode(mode: int) -> int:
    """``mode`` less the process's umask, as ``open`` and ``mkdir`` apply it (0o666 -> 0o644 under umask 022).
    ``tempfile`` creates files 0600 and directories 0700 whatever the umask, too private for a file another
    user (a node in a container with its own UID) must read."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mode & ~mask


def write_atomically(path: Path, write: Callable[[Any], Any]) -> None:
    """Write ``path``: ``write(f)`` into a temp file beside it (binary, mode as the umask says), fsync, then
    os.replace."""
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, umask_mode(0o666))
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


# libyaml's parser where PyYAML was built with it (its wheels are): the same documents as yaml.safe_load, about
# ten times faster, which matters to a node reloading its model while samples keep arriving (the pure-Python
# parser held the interpreter for ~180 ms on a Panda model).
SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def read_yaml(path: str | os.PathLike, error: type[Exception], what: str, missing_fix: str, fix: str,
              syntax_fix: str = "fix the syntax") -> Any:
    """The parsed YAML document at ``path``; ``error`` with the path, what went wrong and the fix
    when the file is missing, unreadable (not text, a directory, no permission) or not YAML."""
    try:
        return yaml.load(Path(path).read_text(), Loader=SAFE_LOADER)
    except FileNotFoundError as exc:
        raise error(f"{path}: {what} not found; {missing_fix}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or "not a text file"
        raise error(f"{path}: cannot read the {what} ({reason}); {fix}") from exc
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{path}: invalid YAML{line}; {syntax_fix}") from exc
