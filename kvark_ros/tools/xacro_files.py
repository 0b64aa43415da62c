"""Expand a xacro file to URDF without a ROS install (for ``kvark init --xacro``).

The PyPI ``xacro`` package resolves ``$(find pkg)`` through ``ament_index_python``, which only a ROS
install has. Here ``$(find pkg)`` (also ``find('pkg')`` in ``$(eval ...)``) and ``package://pkg/...``
in included file names resolve to the folders given as ``--package-path pkg=DIR``; the library's
hooks are replaced only while one file is expanded. ``package://`` URIs in the expanded URDF (mesh
file names) are kept as written: the dynamics never open a mesh.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import xacro
from xacro import substitution_args

from kvark_ros.core.config import ConfigError

__all__ = ["expand_xacro", "parse_assignments"]

_PACKAGE = "package://"


def parse_assignments(items: Sequence[str], separator: str, flag: str, example: str) -> dict[str, str]:
    """``NAME<separator>VALUE`` flag values as a dict (``--package-path pkg=DIR``, ``--xacro-arg k:=v``)."""
    out: dict[str, str] = {}
    for item in items:
        name, found, value = item.partition(separator)
        if not found or not name.strip():
            raise ConfigError(f"{flag} {item!r}: expected {example}")
        out[name.strip()] = value
    return out


@contextmanager
def _hooks(packages: dict[str, Path], missing: list[str]) -> Iterator[None]:
    """While active, xacro's ``find`` and included ``package://`` names use ``packages``; an unknown package is
    recorded in ``missing`` (xacro wraps every exception, so the caller reports it)."""
    def find(package: str) -> str:
        if package not in packages:
            missing.append(package)
            raise LookupError(package)
        return str(packages[package])

    original_abs = xacro.abs_filename_spec

    def abs_filename(spec: str) -> str:
        if spec.startswith(_PACKAGE):
            package, _, rest = spec[len(_PACKAGE):].partition("/")
            return os.path.join(find(package), rest)
        return original_abs(spec)

    saved = (substitution_args._eval_find, substitution_args._eval_dict["find"], original_abs)
    substitution_args._eval_find = substitution_args._eval_dict["find"] = find
    xacro.abs_filename_spec = abs_filename
    try:
        yield
    finally:
        substitution_args._eval_find, substitution_args._eval_dict["find"], xacro.abs_filename_spec = saved


def _undefined_argument(exc: BaseException) -> str | None:
    """The name of an undefined ``$(arg NAME)`` somewhere in xacro's chain of wrapped exceptions."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, substitution_args.ArgException):
            return str(seen)
        seen = getattr(seen, "exc", None) or seen.__cause__
    return None


def expand_xacro(path: Path, packages: dict[str, Path], arguments: dict[str, str]) -> str:
    """The URDF text of a xacro file; one ConfigError naming the file and the fix for every failure."""
    if not path.is_file():
        raise ConfigError(f"{path}: xacro file not found; check --xacro")
    for name, folder in packages.items():
        if not folder.is_dir():
            raise ConfigError(f"--package-path {name}={folder}: no such directory")
    missing: list[str] = []
    try:
        with _hooks(packages, missing):
            document = xacro.process_file(str(path), mappings=dict(arguments))
    except Exception as exc:   # xacro raises XacroException, expat and substitution errors, wrapped in each other
        if missing:
            raise ConfigError(f"{path}: package {missing[0]!r} is not known ($(find {missing[0]}) or "
                              f"package://{missing[0]}/); add --package-path {missing[0]}=DIR (its share "
                              f"folder, the one holding package.xml)") from exc
        name = _undefined_argument(exc)
        if name is not None:
            raise ConfigError(f"{path}: xacro argument {name!r} is undefined; pass --xacro-arg {name}:=VALUE") from exc
        detail = " ".join(str(exc).split())
        raise ConfigError(f"{path}: xacro failed ({detail}); fix the file or the --xacro-arg values") from exc
    return str(document.toprettyxml(indent="  "))
