"""Plant files: how the simulated robot differs from its URDF (docs/method.md §10).

A plant file is YAML; every key is optional and a missing key means "as the URDF"::

    friction:                       # joint friction τ_f(q̇), N·m
      model: gaz_sigmoid            # gaz_sigmoid | coulomb_viscous | stribeck
      phi1: [...]                   # gaz_sigmoid: N·m
      phi2: [...]                   # gaz_sigmoid: s/rad
      phi3: [...]                   # gaz_sigmoid: rad/s
      coulomb: [...]                # coulomb_viscous, stribeck: N·m
      static: [...]                 # stribeck: breakaway level, N·m
      stribeck_velocity: [...]      # stribeck: rad/s
      viscous: [...]                # any model: N·m·s/rad
    armature: [...]                 # rotor inertia reflected to the joint, kg·m²
    payload: {mass: kg, com: [x, y, z] m, inertia: [ixx, iyy, izz, ixy, ixz, iyz] kg·m²}
    drive_gain: [...]               # the joint produces drive_gain × commanded torque
    torque_offset: [...]            # N·m added by the drive
    position_ripple: {amplitude: [...] N·m, cycles_per_rev: [...]}   # amplitude·sin(cycles·q)
    joint_offset: [...]             # rad, encoder zero error: the encoder reads q + joint_offset
    noise: {torque_std: N·m, torque_std_per_rad_s: N·m·s/rad, encoder_counts_per_rev: int}
    control_rate_hz: 1000           # 1000 or 500: rate of the simulated controller

Per-joint values are lists of n numbers in joint order; the noise standard deviations may also
be a single number for every joint. Dynamics of the plant (joint j):

    M q̈ + C q̇ + g + τ_f(q̇) = drive_gain ⊙ τ_m + torque_offset + ripple(q) + τ_ext

with M including armature and payload, all evaluated at the true q. A joint offset is a sensor
effect only: the recorded (and controlled) position is ``q + joint_offset`` (then quantised), so a
model evaluated at the recorded position misses ``g(q) − g(q + δ) ≈ −∂g/∂q δ``.
Bags never carry the plant file.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt
from scipy.special import expit

from kvark_ros.core.files import read_yaml
from kvark_ros.core.payload import Payload

FloatArray = npt.NDArray[np.float64]
PLANT_DIR = Path(__file__).resolve().parent / "plants"
FRICTION_MODELS = ("none", "gaz_sigmoid", "coulomb_viscous", "stribeck")
CONTROL_RATES_HZ = (1000.0, 500.0)
ORACLE_VARIANCE = 1e-4   # N²·m²: the oracle's residual is exact up to the plant's noise
_FRICTION_PARAMETERS = {
    "none": ("viscous",),
    "gaz_sigmoid": ("phi1", "phi2", "phi3", "viscous"),
    "coulomb_viscous": ("coulomb", "viscous"),
    "stribeck": ("coulomb", "static", "stribeck_velocity", "viscous"),
}
_REQUIRED = {"gaz_sigmoid": ("phi1", "phi2", "phi3"), "coulomb_viscous": ("coulomb",),
             "stribeck": ("coulomb", "static", "stribeck_velocity")}
_TOP_KEYS = ("friction", "armature", "payload", "drive_gain", "torque_offset", "position_ripple",
             "joint_offset", "noise", "control_rate_hz")


def _frozen(values: Any) -> FloatArray:
    """Read-only float64 copy, so a frozen PlantSpec stays frozen."""
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class PlantSpec:
    """A parsed plant file for an n-joint arm; arrays are (n,) and read-only."""

    n: int
    friction_model: str
    phi1: FloatArray
    phi2: FloatArray
    phi3: FloatArray
    coulomb: FloatArray
    static: FloatArray
    stribeck_velocity: FloatArray
    viscous: FloatArray
    armature: FloatArray
    payload: Payload | None
    drive_gain: FloatArray
    torque_offset: FloatArray
    ripple_amplitude: FloatArray
    ripple_cycles: FloatArray
    joint_offset: FloatArray
    torque_std: FloatArray
    torque_std_per_rad_s: FloatArray
    encoder_counts_per_rev: int | None
    control_rate_hz: float = 1000.0

    @property
    def encoder_resolution(self) -> float:
        """Position quantum, rad (0 when positions are not quantised)."""
        return 0.0 if self.encoder_counts_per_rev is None else 2.0 * math.pi / self.encoder_counts_per_rev

    @property
    def dry_friction(self) -> bool:
        """True when friction has a Coulomb part (simulated as MuJoCo dry friction, with stiction)."""
        return self.friction_model in ("coulomb_viscous", "stribeck")


class PlantError(ValueError):
    """A plant file or value is invalid; the message names the file and the key."""


def load_plant(source: str | os.PathLike[str] | Mapping[str, Any] | None, n_joints: int) -> PlantSpec:
    """Parse a plant file (path or already-loaded mapping; None = exactly the URDF).

    Raises PlantError naming the offending key (and the file) on any bad value.
    """
    where = "plant"
    if source is None:
        data: Any = {}
    elif isinstance(source, Mapping):
        data = source
    else:
        where = os.fspath(source)
        fix = f"pass an existing plant file such as {default_plant_path('panda')}"
        data = read_yaml(where, PlantError, "plant file", fix, fix) or {}
    if not isinstance(data, Mapping):
        raise PlantError(f"{where}: a plant file is a mapping of keys {list(_TOP_KEYS)}")
    return _Parser(where, n_joints).parse(data)


def default_plant_path(robot: str) -> Path:
    """The plant file shipped for ``robot`` (``panda`` or ``ur5``)."""
    return PLANT_DIR / f"{robot}_default.yaml"


class _Parser:
    """Validates one plant mapping; every error message names file and key."""

    def __init__(self, where: str, n: int) -> None:
        self.where = where
        self.n = n

    def fail(self, key: str, problem: str) -> PlantError:
        """The error for a bad value at ``key``."""
        return PlantError(f"{self.where}: {key} {problem}")

    def mapping(self, value: Any, key: str, allowed: tuple[str, ...]) -> Mapping[str, Any]:
        """``value`` as a mapping whose keys are all in ``allowed``."""
        if not isinstance(value, Mapping):
            raise self.fail(key, f"must be a mapping with keys {list(allowed)}")
        unknown = sorted(set(map(str, value)) - set(allowed))
        if unknown:
            raise self.fail(f"{key}.{unknown[0]}" if key else unknown[0],
                            f"is not a known key; known: {list(allowed)}")
        return value

    def vector(self, value: Any, key: str, minimum: float | None = None, positive: bool = False,
               scalar_ok: bool = False) -> FloatArray:
        """(n,) finite floats; optionally ≥ minimum or > 0; a scalar broadcasts if allowed."""
        given = value
        if scalar_ok and isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * self.n
        if not isinstance(value, (list, tuple)) or len(value) != self.n:
            raise self.fail(key, f"must be a list of {self.n} numbers (one per joint), got {value!r}")
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise self.fail(key, f"must hold numbers only, got {given!r}")
        arr = np.array(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise self.fail(key, f"must hold {self.n} finite numbers, got {given!r}")
        if positive and np.any(arr <= 0.0):
            raise self.fail(key, f"must be > 0 for every joint, got {given!r}")
        if minimum is not None and np.any(arr < minimum):
            raise self.fail(key, f"must be >= {minimum} for every joint, got {given!r}")
        return arr

    def parse(self, data: Mapping[str, Any]) -> PlantSpec:
        """The PlantSpec of a whole plant mapping."""
        self.mapping(data, "", _TOP_KEYS)
        zeros, ones = np.zeros(self.n), np.ones(self.n)
        friction = self.friction(data.get("friction"))
        ripple = self.mapping(data.get("position_ripple") or {}, "position_ripple",
                              ("amplitude", "cycles_per_rev"))
        if ("amplitude" in ripple) != ("cycles_per_rev" in ripple):
            raise self.fail("position_ripple", "needs both amplitude and cycles_per_rev")
        noise = self.mapping(data.get("noise") or {}, "noise",
                             ("torque_std", "torque_std_per_rad_s", "encoder_counts_per_rev"))
        counts = noise.get("encoder_counts_per_rev")
        if counts is not None and (isinstance(counts, bool) or not isinstance(counts, int) or counts < 2):
            raise self.fail("noise.encoder_counts_per_rev", f"must be an integer >= 2, got {counts!r}")
        rate = data.get("control_rate_hz", 1000.0)
        if (isinstance(rate, bool) or not isinstance(rate, (int, float))
                or float(rate) not in CONTROL_RATES_HZ):
            raise self.fail("control_rate_hz", f"must be one of {list(CONTROL_RATES_HZ)} Hz "
                                               f"(the physics runs at 1 kHz), got {rate!r}")

        def get(section: Mapping[str, Any], key: str, label: str, default: FloatArray,
                **kw: Any) -> FloatArray:
            value = section.get(key)
            return _frozen(default if value is None else self.vector(value, label, **kw))

        return PlantSpec(
            n=self.n,
            friction_model=friction.pop("model"),
            **{k: _frozen(v) for k, v in friction.items()},
            armature=get(data, "armature", "armature", zeros, minimum=0.0),
            payload=self.payload(data["payload"]) if data.get("payload") is not None else None,
            drive_gain=get(data, "drive_gain", "drive_gain", ones, positive=True),
            torque_offset=get(data, "torque_offset", "torque_offset", zeros),
            ripple_amplitude=get(ripple, "amplitude", "position_ripple.amplitude", zeros),
            ripple_cycles=get(ripple, "cycles_per_rev", "position_ripple.cycles_per_rev", zeros,
                              minimum=0.0),
            joint_offset=get(data, "joint_offset", "joint_offset", zeros),
            torque_std=get(noise, "torque_std", "noise.torque_std", zeros, minimum=0.0,
                           scalar_ok=True),
            torque_std_per_rad_s=get(noise, "torque_std_per_rad_s", "noise.torque_std_per_rad_s",
                                     zeros, minimum=0.0, scalar_ok=True),
            encoder_counts_per_rev=counts,
            control_rate_hz=float(rate),
        )

    def friction(self, section: Any) -> dict[str, Any]:
        """Friction parameters of the chosen model; unused parameters are an error."""
        params: dict[str, Any] = {key: np.zeros(self.n) for key in
                                  ("phi1", "phi2", "phi3", "coulomb", "static", "viscous")}
        params["stribeck_velocity"] = np.ones(self.n)
        if section is None:
            params["model"] = "none"
            return params
        every = ("model", "phi1", "phi2", "phi3", "coulomb", "static", "stribeck_velocity", "viscous")
        section = self.mapping(section, "friction", every)
        model = section.get("model")
        if model not in _FRICTION_PARAMETERS or model == "none":
            raise self.fail("friction.model", f"must be one of {list(FRICTION_MODELS[1:])}, got {model!r}")
        for key in section:
            if key != "model" and key not in _FRICTION_PARAMETERS[model]:
                raise self.fail(f"friction.{key}", f"is not a parameter of model {model}; "
                                                   f"it takes {list(_FRICTION_PARAMETERS[model])}")
        for key in _REQUIRED[model]:
            if section.get(key) is None:
                raise self.fail(f"friction.{key}", f"is required by model {model}")
        for key in _FRICTION_PARAMETERS[model]:
            if section.get(key) is not None:
                signed = key == "phi3"
                params[key] = self.vector(section[key], f"friction.{key}",
                                          minimum=None if signed else 0.0,
                                          positive=key in ("phi2", "stribeck_velocity"))
        params["model"] = model
        return params

    def payload(self, section: Any) -> Payload:
        """A rigid payload; its inertia must be physically possible (PSD, triangle inequality)."""
        section = self.mapping(section, "payload", ("mass", "com", "inertia"))
        mass = section.get("mass")
        if (isinstance(mass, bool) or not isinstance(mass, (int, float)) or not math.isfinite(mass)
                or mass <= 0):
            raise self.fail("payload.mass", f"must be a number > 0 kg, got {mass!r}")
        com = self._fixed(section.get("com", [0.0, 0.0, 0.0]), 3, "payload.com")
        inertia = self._fixed(section.get("inertia", [0.0] * 6), 6, "payload.inertia")
        ixx, iyy, izz, ixy, ixz, iyz = inertia
        principal = np.linalg.eigvalsh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
        tol = 1e-12 + 1e-9 * float(np.abs(principal).max())
        if principal.min() < -tol or 2.0 * principal.max() > principal.sum() + tol:
            raise self.fail("payload.inertia", f"is not a physical inertia (needs positive "
                                               f"semi-definite, triangle inequality), got {list(inertia)}")
        return Payload(float(mass), cast(tuple[float, float, float], com),
                       cast(tuple[float, float, float, float, float, float], inertia))

    def _fixed(self, value: Any, size: int, key: str) -> tuple[float, ...]:
        """Exactly ``size`` finite floats."""
        try:
            out = tuple(float(v) for v in value)
        except (TypeError, ValueError):
            raise self.fail(key, f"must be a list of {size} numbers, got {value!r}") from None
        if len(out) != size or not all(math.isfinite(v) for v in out):
            raise self.fail(key, f"must be a list of {size} finite numbers, got {value!r}")
        return out


def friction_torque(spec: PlantSpec, qd: npt.ArrayLike) -> FloatArray:
    """Joint friction τ_f(q̇), N·m, for velocities (…, n) rad/s; same shape.

    gaz_sigmoid (Gaz et al., RA-L 2019): ``φ1/(1+e^{−φ2(q̇+φ3)}) − φ1/(1+e^{−φ2 φ3})``;
    coulomb_viscous: ``F_c sign(q̇)``; stribeck: ``(F_c + (F_s − F_c) e^{−(q̇/v_s)²}) sign(q̇)``;
    every model adds ``viscous · q̇``. The dry-friction models are the sliding law: at q̇ = 0
    the plant holds any torque within the friction level, which no function of q̇ can say.
    """
    qd = np.asarray(qd, dtype=float)
    torque = spec.viscous * qd
    if spec.friction_model == "gaz_sigmoid":
        torque = torque + spec.phi1 * (expit(spec.phi2 * (qd + spec.phi3)) - expit(spec.phi2 * spec.phi3))
    elif spec.dry_friction:
        torque = torque + dry_friction_level(spec, qd) * np.sign(qd)
    return torque


class OracleResidual:
    """The plant's true friction as a residual model, for the ``oracle`` observer.

    ``predict(q̇)`` (n,) rad/s gives ``(τ_f(q̇), variance)``, (n,) N·m and (n,) N²·m²: the
    ``ResidualPredictor`` of ``kvark_ros.core.observers.base``, passed to ``make_observer`` and
    ``Estimator.from_config`` as ``oracle``.
    """

    def __init__(self, plant: PlantSpec, n: int) -> None:
        self.plant = plant
        self._variance = np.full(n, ORACLE_VARIANCE)

    @property
    def n_joints(self) -> int:
        return len(self._variance)

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return friction_torque(self.plant, qd), self._variance


def dry_friction_level(spec: PlantSpec, qd: npt.ArrayLike) -> FloatArray:
    """Magnitude of the dry (Coulomb/Stribeck) friction at velocity q̇, N·m (0 without one)."""
    qd = np.asarray(qd, dtype=float)
    if spec.friction_model == "stribeck":
        return spec.coulomb + (spec.static - spec.coulomb) * np.exp(-np.square(qd / spec.stribeck_velocity))
    if spec.friction_model == "coulomb_viscous":
        return np.broadcast_to(spec.coulomb, qd.shape).copy()
    return np.zeros(qd.shape)


def ripple_torque(spec: PlantSpec, q: npt.ArrayLike) -> FloatArray:
    """Position-periodic drive torque ``amplitude · sin(cycles_per_rev · q)``, N·m."""
    return spec.ripple_amplitude * np.sin(spec.ripple_cycles * np.asarray(q, dtype=float))


def actuator_torque(spec: PlantSpec, q: npt.ArrayLike, tau_m: npt.ArrayLike) -> FloatArray:
    """Torque the drives apply for a command τ_m, N·m: ``drive_gain ⊙ τ_m + offset + ripple(q)``.

    This is the noise-free "measured effort" of the simulated robot.
    """
    return spec.drive_gain * np.asarray(tau_m, dtype=float) + spec.torque_offset + ripple_torque(spec, q)


def plant_effects(spec: PlantSpec, q: npt.ArrayLike, qd: npt.ArrayLike) -> FloatArray:
    """Joint torques the nominal model lacks, N·m, in the τ_f slot of the dynamics:

    ``M q̈ + C q̇ + g + plant_effects(q, q̇) = drive_gain ⊙ τ_m + τ_ext``, i.e.
    ``τ_f(q̇) − torque_offset − ripple(q)``. Armature and payload are inertia (inside M);
    the drive gain multiplies τ_m and is not a function of the state.
    """
    return friction_torque(spec, qd) - spec.torque_offset - ripple_torque(spec, q)


def residual_torque(spec: PlantSpec, q: npt.ArrayLike, qd: npt.ArrayLike, qdd: npt.ArrayLike,
                    tau_m: npt.ArrayLike) -> FloatArray:
    """True ``τ_m − τ_EL`` of a payload-free, contact-free motion, N·m (paper eq. 27).

    ``(1 − drive_gain) ⊙ τ_m + plant_effects(q, q̇) + armature ⊙ q̈``: what a perfect residual
    model would learn (the oracle's residual). q is the true position; a ``joint_offset`` adds
    ``g(q) − g(q + joint_offset)`` to the gap seen at the recorded position, which needs the
    robot model and is not included here.
    """
    return ((1.0 - spec.drive_gain) * np.asarray(tau_m, dtype=float) + plant_effects(spec, q, qd)
            + spec.armature * np.asarray(qdd, dtype=float))


def effort_noise_std(spec: PlantSpec, qd: npt.ArrayLike) -> FloatArray:
    """Standard deviation of the measured-effort noise, ``torque_std + torque_std_per_rad_s·|q̇|``, N·m."""
    return spec.torque_std + spec.torque_std_per_rad_s * np.abs(np.asarray(qd, dtype=float))
