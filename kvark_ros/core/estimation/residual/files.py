"""Files and parameter checks shared by every residual model.

Each model writes its own pair in the model directory: ``<stem>.npz`` (the arrays, read back with
``allow_pickle=False``) and ``<stem>.yaml`` (format version, sizes, the hyperparameters as lists,
metadata). No object serialisation anywhere.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from kvark_ros.core.files import read_yaml, write_atomically

FORMAT_VERSION = 1


class ResidualModelError(ValueError):
    """Invalid residual-model parameters, or a model file that cannot be loaded."""


def frozen_float_array(name: str, value: Any, ndim: int) -> np.ndarray:
    """Return a read-only float64 copy of `value`, checked to be finite with `ndim` dimensions."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ResidualModelError(f"{name} is not a numeric array ({exc})") from exc
    if array.ndim != ndim:
        raise ResidualModelError(
            f"{name} must have {ndim} dimension(s), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ResidualModelError(f"{name} contains non-finite values")
    array.setflags(write=False)
    return array


def freeze_positive_vectors(instance: Any, keys: Sequence[str]) -> None:
    """Replace each field ``keys`` of a frozen dataclass by a read-only float vector, all > 0, one length."""
    for key in keys:
        array = frozen_float_array(key, getattr(instance, key), ndim=1)
        if np.any(array <= 0.0):
            raise ResidualModelError(f"{key} must be strictly positive, got {array}")
        object.__setattr__(instance, key, array)
    shapes = {getattr(instance, key).shape for key in keys}
    if len(shapes) != 1:
        raise ResidualModelError(f"hyperparameter arrays differ in shape: {shapes}")


def _header_text(header: Mapping[str, Any]) -> str:
    try:
        return yaml.safe_dump(dict(header), sort_keys=False)
    except yaml.YAMLError as exc:
        raise ValueError(f"metadata must contain plain YAML types only ({exc})") from exc


def save_model_pair(directory: str | os.PathLike, stem: str, arrays: Mapping[str, np.ndarray],
                    header: Mapping[str, Any]) -> None:
    """Write directory/<stem>.npz then directory/<stem>.yaml, each atomically (temp + rename).

    The npz is written first, so a crash in between leaves the previous header, which then
    disagrees with the new arrays and load() refuses the pair instead of mixing them.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    text = _header_text(header)
    write_atomically(directory / f"{stem}.npz", lambda f: np.savez(f, **arrays))
    write_atomically(directory / f"{stem}.yaml", lambda f: f.write(text.encode()))


def check_listed_values(yaml_path: Path, npz_path: Path, listed: Any, arrays: Mapping[str, np.ndarray],
                        keys: tuple[str, ...]) -> None:
    """The values listed in the YAML header must equal the arrays in the npz (same save)."""
    if not isinstance(listed, dict):
        raise ResidualModelError(f"{yaml_path}: missing 'hyperparameters' mapping")
    for key in keys:
        try:
            agrees = np.allclose(np.asarray(listed.get(key), dtype=np.float64), arrays[key],
                                 rtol=1e-12, atol=0.0)
        except (TypeError, ValueError):
            agrees = False
        if not agrees:
            raise ResidualModelError(
                f"{yaml_path}: {key!r} = {listed.get(key)} disagrees with {npz_path} "
                f"({arrays[key].tolist()}); the files are not from the same save")


def read_model_header(path: Path, int_keys: tuple[str, ...], model: str | None = None) -> dict[str, Any]:
    """Read and check a model's YAML header (format version, ``model`` name if given, positive
    integers ``n_joints`` and ``int_keys``, optional ``metadata`` mapping); ResidualModelError naming
    ``path`` on any problem. Shared by KMP and the baselines' models."""
    header = read_yaml(path, ResidualModelError, "model header", "retrain the model", "retrain the model",
                       "retrain the model")
    if not isinstance(header, dict):
        raise ResidualModelError(f"{path}: expected a mapping at top level")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise ResidualModelError(
            f"{path}: unknown format_version {version!r} (this code reads {FORMAT_VERSION})")
    if model is not None and header.get("model") != model:
        raise ResidualModelError(f"{path}: model is {header.get('model')!r}, expected {model!r}")
    for key in ("n_joints",) + int_keys:
        value = header.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ResidualModelError(f"{path}: {key} must be a positive integer, got {value!r}")
    metadata = header.get("metadata") or {}
    if not isinstance(metadata, dict):
        raise ResidualModelError(f"{path}: 'metadata' must be a mapping")
    header["metadata"] = metadata
    return header


def read_arrays(path: Path, shapes: Mapping[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """Read the arrays named in `shapes` from an npz (object arrays refused); check shape and values."""
    arrays: dict[str, np.ndarray] = {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            for key, shape in shapes.items():
                if key not in npz.files:
                    raise ResidualModelError(f"{path}: missing array {key!r}")
                array = npz[key]
                if array.shape != shape:
                    raise ResidualModelError(
                        f"{path}: array {key!r} has shape {array.shape}, expected {shape}")
                if array.dtype.kind not in "fiu":
                    raise ResidualModelError(
                        f"{path}: array {key!r} has non-numeric dtype {array.dtype}")
                if not np.all(np.isfinite(array)):
                    raise ResidualModelError(f"{path}: array {key!r} has non-finite values")
                arrays[key] = array.astype(np.float64)
    except ResidualModelError:
        raise
    except (OSError, EOFError, ValueError, zipfile.BadZipFile) as exc:
        # ValueError includes numpy's refusal of object arrays; its text suggests an unsafe load.
        raise ResidualModelError(f"{path}: corrupt or not a kvark model file ({type(exc).__name__}); "
                                 "retrain the model with `kvark train`") from exc
    return arrays
