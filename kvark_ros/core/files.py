"""Files: atomic writes (a reader sees the old file or the new one, never half of one), the one rule for a
command's output (an existing non-empty output is replaced only with ``--force``, built beside it and swapped in
whole) and YAML reads whose every failure is one user error naming the file, the problem and the fix."""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

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


class OutputExistsError(ValueError):
    """A command's output exists and is not empty and ``--force`` was not given (a user error: one line)."""


def _occupied(path: Path) -> bool:
    """Whether ``path`` holds something an output would replace: a link, a non-empty file or directory."""
    if path.is_symlink():
        return True
    if path.is_dir():
        return any(path.iterdir())
    return path.exists() and path.stat().st_size > 0


def check_output(path: str | os.PathLike, force: bool, inputs: Iterable[str | os.PathLike | None] = ()) -> None:
    """The output rule of every command that writes: ``path`` may be new or an empty directory (or file); anything
    else is replaced only with ``force``, and never when it holds the current directory or one of the command's
    ``inputs`` (bags, models, logs: the swap would delete them). Called before the long work, so a refusal costs
    nothing."""
    if not force and _occupied(Path(path)):
        raise OutputExistsError(f"{os.fspath(path)}: exists and is not empty; pass --force to replace it or choose "
                                "another --out")
    if not force:
        return
    target, here = Path(path).resolve(), Path.cwd()
    if target in (here, *here.parents):
        raise OutputExistsError(f"{os.fspath(path)}: holds the current directory, which --force would replace; "
                                "choose another --out")
    for source in filter(None, inputs):
        resolved = Path(source).resolve()
        if resolved == target or target in resolved.parents:
            raise OutputExistsError(f"{os.fspath(path)}: holds the input {os.fspath(source)}, which --force would "
                                    "replace; choose another --out")


def replace_path(built: Path, target: Path) -> None:
    """Move ``built`` (a directory or file) onto ``target`` by renames; the previous ``target`` is set aside
    first and removed only after, and put back on any failure."""
    backup = target.with_name(f".{target.name}.previous")
    _remove(backup)
    had_target = target.exists() or target.is_symlink()
    try:
        if had_target:
            os.replace(target, backup)
        os.replace(built, target)
    except BaseException:
        if had_target and not (target.exists() or target.is_symlink()):
            os.replace(backup, target)
        raise
    _remove(backup)


def _remove(path: Path) -> None:
    """Delete ``path`` whatever it is (a directory tree, a file, a link); nothing if it does not exist."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def staged_directory(target: str | os.PathLike, force: bool) -> Iterator[Path]:
    """A new empty directory beside ``target`` to build the output in; when the block succeeds it replaces
    ``target`` whole (``replace_path``), so no file of an old output survives, and when the block fails it is
    removed and ``target`` is untouched. ``check_output`` is applied before and again at the swap (an output that
    appeared meanwhile)."""
    target = Path(target)
    check_output(target, force)
    target.absolute().parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.absolute().parent))
    try:
        staging.chmod(umask_mode(0o777))          # it becomes the output: readable as mkdir makes it
        yield staging
        check_output(target, force)
        replace_path(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


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
