"""A model directory: the KMP residual model, the filter tuning and where they came from.

Layout: ``model.yaml`` (robot, joint names, filter tunings, momentum-noise levels, provenance)
beside the residual models' files: ``kmp.npz``/``kmp.yaml`` for K-VARK and, when trained, the
baselines' ``gmr_gp``, ``sparse_gp`` and ``mlp`` files, and ``augmentation.yaml`` when the model was
trained on a model augmented by ``kvark diagnose`` (the residuals are relative to that model, so
the estimator must use the same augmentation). Saving builds the whole directory next to the target and
swaps it in with renames, so a failed save never leaves a half-written or broken model.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from kvark_ros import __version__
from kvark_ros.core.estimation.augmentation import Augmentation, AugmentationError, parse_augmentation
from kvark_ros.core.files import read_yaml, staged_directory
from kvark_ros.core.estimation.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.residual import LEARNED_BASELINES, KMPResidualModel, ResidualModelError
from kvark_ros.core.estimation.calibration import IntervalScale
from kvark_ros.core.estimation.stiction import StictionBand

MODEL_FILE = "model.yaml"
AUGMENTATION_FILE = "augmentation.yaml"
MODEL_FORMAT = 1


@dataclass(frozen=True)
class TrainedModel:
    """What the estimators need from training.

    residual: the KMP model; tuning: its filter tuning. baselines: the learned-residual
    baselines by observer name (``gmr_gp``, ``gpadkf``, ``nnadkf``) with their own tunings in
    ``baseline_tunings``. momentum_noise: noise levels of the residual-free momentum observers.
    augmentation: the model augmentation the residuals were computed against, if any.
    """

    robot: str
    joint_names: tuple[str, ...]
    residual: KMPResidualModel
    tuning: FilterTuning
    info: dict[str, Any] = field(default_factory=dict)   # provenance: bags, hashes, hyperparameters
    baselines: Mapping[str, Any] = field(default_factory=dict)
    baseline_tunings: Mapping[str, FilterTuning] = field(default_factory=dict)
    momentum_noise: MomentumNoise | None = None
    augmentation: Augmentation | None = None
    sample_period: float = DEFAULT_SAMPLE_PERIOD   # t_s, s: median period of the training data
    stiction: StictionBand | None = None           # static friction band per joint (None: not identified)
    interval_scale: IntervalScale | None = None    # kvark's reported-interval factors (None: not calibrated)

    @property
    def sample_rate(self) -> float:
        """The rate the model was trained at, Hz (1 / t_s)."""
        return 1.0 / self.sample_period


def save_model(directory: str | os.PathLike, model: TrainedModel) -> None:
    """Write ``model`` to ``directory`` atomically (replacing an existing model only on success)."""
    with staged_directory(directory, force=True) as staging:
        write_model_files(staging, model)


def write_model_files(directory: Path, model: TrainedModel) -> None:
    """The model's files in the existing, empty ``directory`` (``save_model`` stages them; ``kvark train`` adds
    its plots before the swap)."""
    model.residual.save(directory)
    for baseline in model.baselines.values():
        baseline.save(directory)
    # info (long, free-form) comes before the keys load_model requires, so a file cut short anywhere in it
    # lacks them and is refused.
    document = {"format": MODEL_FORMAT, "kvark_ros_version": __version__, "robot": model.robot,
                "joint_names": list(model.joint_names), "info": model.info,
                "filter_tuning": model.tuning.to_dict(),
                "baselines": {name: model.baseline_tunings[name].to_dict() for name in model.baselines},
                "momentum_noise": None if model.momentum_noise is None else model.momentum_noise.to_dict(),
                "augmentation_sha256": None if model.augmentation is None else model.augmentation.sha256,
                "sample_rate_hz": model.sample_rate,
                "stiction": None if model.stiction is None else model.stiction.to_dict(),
                "interval_scale": None if model.interval_scale is None else model.interval_scale.to_dict()}
    if model.augmentation is not None:
        (directory / AUGMENTATION_FILE).write_text(model.augmentation.text)
    (directory / MODEL_FILE).write_text(yaml.safe_dump(document, sort_keys=False))


def load_model(directory: str | os.PathLike, joint_names: tuple[str, ...] | None = None,
               urdf_sha256: str | None = None, baselines: Iterable[str] | None = None) -> TrainedModel:
    """Read a model directory; ``joint_names`` (the config's) must match the model's exactly, and
    ``urdf_sha256`` (of the URDF the estimator will use) the one the model was trained with, if recorded.

    ``baselines``: the learned baselines to read (None: every one the file lists). An estimator reads the one its
    observer runs, or none: reading the other three is most of a reload's work, done while samples arrive."""
    path = Path(directory) / MODEL_FILE
    if Path(directory).exists() and not Path(directory).is_dir():
        raise ResidualModelError(f"{directory}: not a model directory; pass the directory `kvark train` wrote")
    document = read_yaml(path, ResidualModelError, "model file",
                         "train one with `kvark train` or set residual_model.model_dir", "retrain the model",
                         "retrain the model")
    if not isinstance(document, dict) or document.get("format") != MODEL_FORMAT:
        raise ResidualModelError(f"{path}: unknown model format; expected format {MODEL_FORMAT}, retrain the model")
    try:
        names = tuple(document["joint_names"])
        tuning = FilterTuning.from_dict(document["filter_tuning"])
        robot = str(document["robot"])
        baseline_tunings = {name: FilterTuning.from_dict(values)
                            for name, values in (document.get("baselines") or {}).items()}
        noise = document["momentum_noise"]      # written after info: absent when the file was cut short
        momentum_noise = None if noise is None else MomentumNoise.from_dict(noise)
        # Models written before the rate was recorded were all trained at 500 Hz.
        sample_period = 1.0 / float(document.get("sample_rate_hz", 1.0 / DEFAULT_SAMPLE_PERIOD))
        if not 0.0 < sample_period < 1.0:
            raise ValueError(f"sample_rate_hz {document.get('sample_rate_hz')!r} is not a rate above 1 Hz")
        stiction = None if document.get("stiction") is None else StictionBand.from_dict(document["stiction"])
        scale = document.get("interval_scale")
        interval_scale = None if scale is None else IntervalScale.from_dict(scale)
    except (KeyError, TypeError, ValueError) as exc:
        raise ResidualModelError(f"{path}: incomplete or invalid model file ({exc}); retrain the model") from exc
    if joint_names is not None and tuple(joint_names) != names:
        raise ResidualModelError(f"{path}: model joints {list(names)} differ from the configured "
                                 f"{list(joint_names)}; train a model for these joints")
    trained_urdf = (document.get("info") or {}).get("urdf_sha256")
    if urdf_sha256 is not None and trained_urdf is not None and trained_urdf != urdf_sha256:
        raise ResidualModelError(f"{path}: trained for another URDF (sha256 {trained_urdf[:12]}…, the config's is "
                                 f"{urdf_sha256[:12]}…); retrain with `kvark train` for this robot model")
    residual = KMPResidualModel.load(directory)
    unknown = sorted(set(baseline_tunings) - set(LEARNED_BASELINES))
    if unknown:
        raise ResidualModelError(f"{path}: unknown baseline '{unknown[0]}'; retrain the model")
    if baselines is not None:
        baseline_tunings = {name: value for name, value in baseline_tunings.items() if name in set(baselines)}
    learned = {name: LEARNED_BASELINES[name].load(directory) for name in baseline_tunings}
    augmentation = _load_augmentation(Path(directory), names, document.get("augmentation_sha256"))
    sizes = {residual.n_joints, len(tuning.process_noise_density)}
    sizes |= {model.n_joints for model in learned.values()}
    if interval_scale is not None:
        sizes.add(len(interval_scale.scale))
    if sizes != {len(names)}:
        raise ResidualModelError(f"{path}: residual models and filter tunings disagree on the number of joints")
    return TrainedModel(robot, names, residual, tuning, dict(document.get("info") or {}), learned,
                        baseline_tunings, momentum_noise, augmentation, sample_period, stiction, interval_scale)


def _load_augmentation(directory: Path, joint_names: tuple[str, ...], recorded: str | None) -> Augmentation | None:
    """The model directory's augmentation; it must be there exactly when model.yaml records one."""
    path = directory / AUGMENTATION_FILE
    if recorded is None:
        if path.exists():
            raise ResidualModelError(f"{path}: model.yaml records no augmentation; retrain the model")
        return None
    try:
        augmentation = parse_augmentation(path.read_text(), joint_names, str(path))
    except (OSError, UnicodeDecodeError, AugmentationError) as exc:
        raise ResidualModelError(f"{path}: missing or unreadable ({exc}); retrain the model") from exc
    if augmentation.sha256 != recorded:
        raise ResidualModelError(f"{path}: changed since training (sha256 differs from model.yaml); "
                                 "retrain the model")
    return augmentation
