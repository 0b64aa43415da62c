"""Model augmentation: the physical effects ``kvark diagnose`` named, added to the nominal model.

``augmentation.yaml`` (written by ``kvark diagnose``, docs/method.md §8) lists effects with raw parameters
θ such that, on contact-free motion, ``τ_m − τ_EL ≈ Σ Φ(q, q̇, q̈, τ_m) θ``. The improved model
applies each effect where it physically acts:

* ``payload``   a change of the flange link's 10 inertial parameters (flange frame): an unmodelled tool
  (mass > 0) or a tool mismatch (mass < 0); inside M, C, g; the robot model refuses a change that leaves
  the link physically inconsistent;
* ``link_inertia`` changes of the other links' inertial parameters (10 per link, joint frames): inside M, C, g;
* ``armature``  rotor inertia on the joint diagonal (pinocchio ``model.armature``): inside M;
* ``joint_offset`` the encoder reads ``q + δ``: the model is evaluated at ``q − δ``;
* friction, ``drive_gain``, ``torque_offset``, ``position_ripple``: a joint torque
  ``τ_aug(q, q̇, τ_m) = Σ Φ θ`` the drive spends beyond the rigid body, so the improved model is
  ``M q̈ + C q̇ + g + τ_aug = τ_m + τ_ext``.

``joint_columns`` is the single definition of the torque effects' regressors: the diagnosis fits
θ with it and the estimator evaluates ``τ_aug`` with it. Which effects exist, their kinds, parameter counts and
required settings are those of ``core.effect_catalog``.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import yaml

from kvark_ros.core.effect_catalog import (BODY_PARAMETERS, EFFECTS_BY_NAME, PARAMETERS_PER_JOINT,
                                           REQUIRED_VARIANT, STRUCTURAL_EFFECTS, TANH_EPSILON, TORQUE_EFFECTS)
from kvark_ros.core.files import SAFE_LOADER

PAYLOAD_SIZE = len(BODY_PARAMETERS)


class AugmentationError(ValueError):
    """An augmentation file is unreadable or does not fit the configured robot."""


def joint_columns(name: str, variant: Mapping[str, float], q: np.ndarray, qd: np.ndarray,
                  tau_m: np.ndarray) -> list[np.ndarray]:
    """Regressor columns of a torque effect on one joint's samples (any shape, broadcast).

    Their θ-weighted sum is the effect's share of ``τ_m − τ_EL`` (N·m); θ is the physical
    parameter (see ``kvark_ros.gap.effects`` for each effect's units and sign).
    """
    eps = variant.get("epsilon", TANH_EPSILON)
    if name == "coulomb_friction":
        return [np.tanh(qd / eps)]
    if name == "viscous_friction":
        return [qd]
    if name == "stribeck_friction":
        return [np.exp(-np.square(qd / variant["stribeck_velocity"])) * np.tanh(qd / eps)]
    if name == "drive_gain":            # the drive applies g τ_m: gap (1 − g) τ_m, θ = 1 − g
        return [tau_m]
    if name == "torque_offset":         # the drive applies τ_m + o: gap −o
        return [-np.ones_like(q)]
    if name == "position_ripple":       # the drive applies a sin(k q) + b cos(k q)
        k = variant["cycles_per_rev"]
        return [-np.sin(k * q), -np.cos(k * q)]
    raise ValueError(f"{name!r} is not a torque effect; torque effects: {TORQUE_EFFECTS}")


@dataclass(frozen=True)
class TorqueEffect:
    """One torque effect on joints ``joints`` (int array) with parameters ``theta`` (len(joints), k)."""

    name: str
    joints: np.ndarray
    variant: Mapping[str, float]
    theta: np.ndarray


@dataclass(frozen=True)
class TorqueTerm:
    """One torque effect on one joint: ``joint_torque`` adds Σ_c column_c θ_c to τ_aug of ``joint``, the columns
    ``joint_columns(name, …)`` of the effect's variant."""

    name: str                           # the effect, one of TORQUE_EFFECTS
    joint: int                          # joint index
    epsilon: float                      # tanh width ε of the smoothed sign(q̇), rad/s (TANH_EPSILON by default)
    second: float                       # the effect's required setting (v_s rad/s of Stribeck, k of the ripple), or 0.0
    theta: tuple[float, float]          # θ: (θ₁, θ₂) of the ripple, (θ, 0.0) of the others


@dataclass(frozen=True, eq=False)
class Augmentation:
    """A parsed augmentation for an n-joint model.

    payload: (10,) change of the flange link's dynamic parameters ``[m, m c, I_origin]`` in the flange frame,
    or None; link_inertia: (n − 1, 10) changes of the other links' (joint frames), or None;
    armature: (n,) kg·m²; joint_offset: (n,) rad; torque_effects: the τ_aug terms;
    text: the file's exact text (copied into model directories), sha256: its hash.
    """

    source: str
    joint_names: tuple[str, ...]
    effect_names: tuple[str, ...]
    payload: np.ndarray | None
    link_inertia: np.ndarray | None
    armature: np.ndarray
    joint_offset: np.ndarray
    torque_effects: tuple[TorqueEffect, ...]
    text: str
    sha256: str

    def joint_torque(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
        """``τ_aug(q, q̇, τ_m)`` N·m, q as measured: one sample (n,) or samples (T, n)."""
        total = np.zeros(np.shape(q))
        for effect in self.torque_effects:
            j = effect.joints
            columns = joint_columns(effect.name, effect.variant, q[..., j], qd[..., j], tau_m[..., j])
            for c, column in enumerate(columns):
                total[..., j] += column * effect.theta[:, c]
        return total

    def torque_terms(self) -> tuple[TorqueTerm, ...]:
        """``torque_effects`` one effect and joint at a time, in the order ``joint_torque`` adds them (for a compiled
        τ_aug, ``core.estimation.compiled.residual``)."""
        terms = []
        for effect in self.torque_effects:
            variant = effect.variant
            epsilon = variant.get("epsilon", TANH_EPSILON)
            required = EFFECTS_BY_NAME[effect.name].required     # the effect's one non-linear setting, if any
            second = variant[required[0]] if required else 0.0
            for joint, theta in zip(effect.joints, effect.theta):
                padded = (float(theta[0]), float(theta[1]) if theta.shape[0] > 1 else 0.0)
                terms.append(TorqueTerm(effect.name, int(joint), epsilon, second, padded))
        return tuple(terms)


def _fail(source: str, problem: str) -> AugmentationError:
    return AugmentationError(f"{source}: {problem}; write it with `kvark diagnose` or fix model_augmentation")


def parse_augmentation(text: str, joint_names: Sequence[str], source: str = "augmentation") -> Augmentation:
    """Validate the text of an ``augmentation.yaml`` against the configured joints."""
    try:
        document = yaml.load(text, Loader=SAFE_LOADER)
    except yaml.YAMLError as exc:
        raise _fail(source, "invalid YAML") from exc
    if not isinstance(document, Mapping) or not isinstance(document.get("effects"), list):
        raise _fail(source, "expected a mapping with an 'effects' list")
    names = tuple(document.get("joint_names") or ())
    if names != tuple(joint_names):
        raise _fail(source, f"written for joints {list(names)}, the config has {list(joint_names)}")
    n = len(names)
    payload, links, armature, offset = None, None, np.zeros(n), np.zeros(n)
    torque_effects, effect_names = [], []
    for index, entry in enumerate(document["effects"]):
        where = f"effect {index + 1}"
        try:
            name = str(entry["name"])
            joints = np.array([int(j) for j in entry["joint_indices"]], dtype=int)
            theta = np.asarray(entry["theta"], dtype=float)
            variant = {str(k): float(v) for k, v in (entry.get("variant") or {}).items()}
        except (KeyError, TypeError, ValueError) as exc:
            raise _fail(source, f"{where} needs name, joint_indices, theta (numbers) ({exc})") from exc
        if name not in TORQUE_EFFECTS + STRUCTURAL_EFFECTS:
            raise _fail(source, f"{where}: unknown effect {name!r}")
        if len(joints) == 0 or joints.min() < 0 or joints.max() >= n or len(set(joints.tolist())) != len(joints):
            raise _fail(source, f"{where} ({name}): joint_indices must be distinct indices in 0..{n - 1}")
        if not np.all(np.isfinite(theta)):
            raise _fail(source, f"{where} ({name}): theta has NaN or Inf")
        missing = [key for key in REQUIRED_VARIANT.get(name, ()) if key not in variant]
        if missing:
            raise _fail(source, f"{where} ({name}): variant needs {missing}")
        size = {"payload": PAYLOAD_SIZE, "link_inertia": PAYLOAD_SIZE * (n - 1)}.get(
            name, PARAMETERS_PER_JOINT.get(name, 0) * len(joints))
        if theta.size != size:
            raise _fail(source, f"{where} ({name}): theta has {theta.size} values, expected {size}")
        if name not in effect_names:
            effect_names.append(name)
        # An effect listed again adds to the earlier entry (`kvark diagnose --against` writes the base model's
        # effects followed by those found relative to it); every effect is linear in θ, so the sum is the total.
        if name == "payload":       # physical consistency needs the URDF: checked by the robot model
            payload = theta if payload is None else payload + theta
        elif name == "link_inertia":
            links = theta.reshape(n - 1, PAYLOAD_SIZE) + (0.0 if links is None else links)
        elif name == "armature":
            armature[joints] += theta
            if armature.min() < 0.0:
                raise _fail(source, f"{where} (armature): values must be ≥ 0 kg·m²")
        elif name == "joint_offset":
            offset[joints] += theta
        else:
            k = PARAMETERS_PER_JOINT[name]
            torque_effects.append(TorqueEffect(name, joints, variant, theta.reshape(len(joints), k)))
    return Augmentation(source, names, tuple(effect_names), payload, links, armature, offset, tuple(torque_effects),
                        text, hashlib.sha256(text.encode()).hexdigest())


def load_augmentation(path: str | os.PathLike, joint_names: Sequence[str]) -> Augmentation:
    """Read and validate an ``augmentation.yaml``."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError as exc:
        raise _fail(str(path), "file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(str(path), "cannot read the file (not text)") from exc
    return parse_augmentation(text, joint_names, str(path))
