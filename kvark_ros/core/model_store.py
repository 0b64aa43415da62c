"""A model directory: the KMP residual model, the filter tuning and where they came from.

Layout: ``model.yaml`` (robot, joint names, filter tuning, provenance) beside the residual
model's ``kmp.npz`` and ``kmp.yaml``. Saving builds the whole directory next to the target and
swaps it in with renames, so a failed save never leaves a half-written or broken model.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from kvark_ros import __version__
from kvark_ros.core.observers.base import FilterTuning
from kvark_ros.core.residual_model import KMPResidualModel, ResidualModelError

MODEL_FILE = "model.yaml"
MODEL_FORMAT = 1


@dataclass(frozen=True)
class TrainedModel:
    """What the estimator needs from training."""

    robot: str
    joint_names: tuple[str, ...]
    residual: KMPResidualModel
    tuning: FilterTuning
    info: dict[str, Any] = field(default_factory=dict)   # provenance: bags, hashes, hyperparameters


def save_model(directory: str | os.PathLike, model: TrainedModel) -> None:
    """Write ``model`` to ``directory`` atomically (replacing an existing model only on success)."""
    target = Path(directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        model.residual.save(staging)
        document = {"format": MODEL_FORMAT, "kvark_ros_version": __version__, "robot": model.robot,
                    "joint_names": list(model.joint_names), "filter_tuning": model.tuning.to_dict(),
                    "info": model.info}
        (staging / MODEL_FILE).write_text(yaml.safe_dump(document, sort_keys=False))
        backup = target.with_name(f".{target.name}.previous")
        if target.exists():
            shutil.rmtree(backup, ignore_errors=True)
            os.replace(target, backup)
        os.replace(staging, target)
        shutil.rmtree(backup, ignore_errors=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def load_model(directory: str | os.PathLike, joint_names: tuple[str, ...] | None = None) -> TrainedModel:
    """Read a model directory; ``joint_names`` (the config's) must match the model's exactly."""
    path = Path(directory) / MODEL_FILE
    try:
        document = yaml.safe_load(path.read_text())
    except FileNotFoundError as exc:
        raise ResidualModelError(f"{path}: model file not found; train one with `kvark train` "
                                 "or set residual_model.model_dir") from exc
    except yaml.YAMLError as exc:
        raise ResidualModelError(f"{path}: not valid YAML; retrain the model") from exc
    if not isinstance(document, dict) or document.get("format") != MODEL_FORMAT:
        raise ResidualModelError(f"{path}: unknown model format; expected format {MODEL_FORMAT}, retrain the model")
    try:
        names = tuple(document["joint_names"])
        tuning = FilterTuning.from_dict(document["filter_tuning"])
        robot = str(document["robot"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ResidualModelError(f"{path}: incomplete or invalid model file ({exc}); retrain the model") from exc
    if joint_names is not None and tuple(joint_names) != names:
        raise ResidualModelError(f"{path}: model joints {list(names)} differ from the configured "
                                 f"{list(joint_names)}; train a model for these joints")
    residual = KMPResidualModel.load(directory)
    if residual.n_joints != len(names) or len(tuning.process_noise_density) != len(names):
        raise ResidualModelError(f"{path}: residual model and filter tuning disagree on the number of joints")
    return TrainedModel(robot, names, residual, tuning, dict(document.get("info") or {}))
