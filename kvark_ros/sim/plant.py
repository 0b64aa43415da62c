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
    friction_drift: {relative_amplitude: 0.15, time_constant_s: 300}   # warm-up: τ_f × (1 + a·e^{−t/τ})
    armature: [...]                 # rotor inertia reflected to the joint, kg·m²
    link_inertia:                   # CAD errors of the moving links (child links of the simulated joints)
      <link>: {mass_scale: 1.1, com_shift: [x, y, z] m (link frame), inertia_scale: s | [s1, s2, s3]}
      # or generated, deterministic for the seed:
      # {seed: int, mass_rel: 0.15, com_m: 0.02, inertia_rel: 0.3}
    tool: {urdf_tool: present | absent, extra: {mass: kg, com: [x, y, z] m, inertia: [6] kg·m²}}
    payload: {mass: kg, com: [x, y, z] m, inertia: [ixx, iyy, izz, ixy, ixz, iyz] kg·m²}
    drive_gain: [...]               # the joint produces drive_gain × commanded torque
    torque_offset: [...]            # N·m added by the drive
    torque_offset_drift: {amplitude: [...] N·m, period_s: 120}        # amplitude·sin(2π t / period)
    position_ripple: {amplitude: [...] N·m, cycles_per_rev: [...]}   # amplitude·sin(cycles·q)
    joint_offset: [...]             # rad, encoder zero error: the encoder reads q + joint_offset
    noise: {torque_std: N·m, torque_std_per_rad_s: N·m·s/rad, encoder_counts_per_rev: int}
    control_rate_hz: 1000           # 1000, 500, 125 or 100: rate of the simulated controller

Per-joint values are lists of n numbers in joint order; the noise standard deviations may also
be a single number for every joint. Dynamics of the plant (joint j):

    M q̈ + C q̇ + g + φ(t) τ_f(q̇) = drive_gain ⊙ τ_m + torque_offset + d(t) + ripple(q) + τ_ext

with M, C, g those of the plant's true rigid body (``true_model.true_urdf``: the URDF with the
``link_inertia`` errors, the ``tool`` mismatch and the payload), M also holding the armature, all
evaluated at the true q and the plant clock t (s since power-on, ``MujocoPlant.time``).

``link_inertia``: per link, the mass is multiplied by ``mass_scale``, the centre of mass moves by
``com_shift`` and the principal moments of the rotational inertia about the centre of mass (in
ascending order; a number scales all three) are multiplied by ``inertia_scale``; they must still
obey the triangle inequality. The generated form draws per link (in joint order) a mass scale
1 + U(−mass_rel, mass_rel), a shift uniform in the ball of radius com_m, and scales the three
second moments of the mass distribution about the principal axes (``∫x² dm`` …) by 1 + U(−inertia_rel,
inertia_rel): each principal moment then changes by a factor within 1 ± inertia_rel and the
inertia stays physically valid (positive, triangle inequality) for inertia_rel < 1.
``tool``: ``urdf_tool: absent`` means the robot does not carry the links the URDF fixes after the
flange (the Franka Hand and its fingers): they keep their frames but lose their mass; ``extra``
is a rigid tool welded to the flange that the URDF lacks. Unlike the ``payload`` (a load the
ground truth counts as external torque) the tool is part of the robot: no τ_ext, no wrist F/T.
``friction_drift``: the friction torque (all of φ1, coulomb, static, viscous) is multiplied by
``φ(t) = 1 + relative_amplitude·e^{−t/time_constant_s}``: cold joints have more friction (grease
viscosity) and reach the file's values once warm. ``torque_offset_drift`` adds
``d(t) = amplitude·sin(2π t / period_s)`` to the drive torque like ``torque_offset``.
A joint offset is a sensor effect only: the recorded (and controlled) position is ``q + joint_offset``
(then quantised), so a model evaluated at the recorded position misses ``g(q) − g(q + δ) ≈ −∂g/∂q δ``.
Bags never carry the plant file.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt
from scipy.special import expit

from kvark_ros.core.files import read_yaml
from kvark_ros.core.estimation.payload import Payload

FloatArray = npt.NDArray[np.float64]
PLANT_DIR = Path(__file__).resolve().parent / "plants"
FRICTION_MODELS = ("none", "gaz_sigmoid", "coulomb_viscous", "stribeck")
# Control rates of the simulated controller: each period must be a whole number of 1 ms physics steps.
# 1 kHz Panda (FCI), 500 Hz UR e-Series / UR5 RTDE, 125 Hz UR CB3, 100 Hz as logged by some UR10e datasets.
CONTROL_RATES_HZ = (1000.0, 500.0, 125.0, 100.0)
ORACLE_VARIANCE = 1e-4   # N²·m²: the oracle's residual is exact up to the plant's noise
_FRICTION_PARAMETERS = {
    "none": ("viscous",),
    "gaz_sigmoid": ("phi1", "phi2", "phi3", "viscous"),
    "coulomb_viscous": ("coulomb", "viscous"),
    "stribeck": ("coulomb", "static", "stribeck_velocity", "viscous"),
}
_REQUIRED = {"gaz_sigmoid": ("phi1", "phi2", "phi3"), "coulomb_viscous": ("coulomb",),
             "stribeck": ("coulomb", "static", "stribeck_velocity")}
_TOP_KEYS = ("friction", "friction_drift", "armature", "link_inertia", "tool", "payload", "drive_gain",
             "torque_offset", "torque_offset_drift", "position_ripple", "joint_offset", "noise",
             "control_rate_hz")
_LINK_ERROR_KEYS = ("mass_scale", "com_shift", "inertia_scale")
_LINK_DRAW_KEYS = ("seed", "mass_rel", "com_m", "inertia_rel")


def _frozen(values: Any) -> FloatArray:
    """Read-only float64 copy, so a frozen PlantSpec stays frozen."""
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True)
class LinkError:
    """CAD error of one link: mass × ``mass_scale``, centre of mass + ``com_shift`` (3,) m in the
    link frame, principal moments about the centre of mass (ascending) × ``inertia_scale`` (3,)."""

    mass_scale: float = 1.0
    com_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class LinkErrorDraw:
    """The generated form of ``link_inertia``: bounds of random link errors and the seed that draws
    them (``true_model.link_errors`` draws them against the URDF)."""

    seed: int
    mass_rel: float = 0.0
    com_m: float = 0.0      # m
    inertia_rel: float = 0.0


@dataclass(frozen=True, eq=False)
class PlantSpec:
    """A parsed plant file for an n-joint arm; arrays are (n,) and read-only.

    link_inertia: per-link errors (read-only mapping link → LinkError), their generated form, or None;
    tool_absent: the URDF's links after the flange are not carried; tool: an extra rigid tool at
    the flange; friction_drift: relative amplitude, friction_drift_time_constant: s;
    offset_drift_amplitude: (n,) N·m, offset_drift_period: s; source: the file, for error messages.
    """

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
    offset_drift_amplitude: FloatArray
    ripple_amplitude: FloatArray
    ripple_cycles: FloatArray
    joint_offset: FloatArray
    torque_std: FloatArray
    torque_std_per_rad_s: FloatArray
    encoder_counts_per_rev: int | None
    link_inertia: Mapping[str, LinkError] | LinkErrorDraw | None = None
    tool_absent: bool = False
    tool: Payload | None = None
    friction_drift: float = 0.0
    friction_drift_time_constant: float = math.inf
    offset_drift_period: float = math.inf
    control_rate_hz: float = 1000.0
    source: str = "plant"

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
        tool = self.mapping(data.get("tool") or {}, "tool", ("urdf_tool", "extra"))
        if tool.get("urdf_tool", "present") not in ("present", "absent"):
            raise self.fail("tool.urdf_tool", f"must be present or absent, got {tool['urdf_tool']!r}")
        drift = self.complete(data, "friction_drift", ("relative_amplitude", "time_constant_s"))
        offset_drift = self.complete(data, "torque_offset_drift", ("amplitude", "period_s"))

        def get(section: Mapping[str, Any], key: str, label: str, default: FloatArray,
                **kw: Any) -> FloatArray:
            value = section.get(key)
            return _frozen(default if value is None else self.vector(value, label, **kw))

        return PlantSpec(
            n=self.n,
            friction_model=friction.pop("model"),
            **{k: _frozen(v) for k, v in friction.items()},
            armature=get(data, "armature", "armature", zeros, minimum=0.0),
            payload=self.rigid_body(data["payload"], "payload") if data.get("payload") is not None else None,
            drive_gain=get(data, "drive_gain", "drive_gain", ones, positive=True),
            torque_offset=get(data, "torque_offset", "torque_offset", zeros),
            offset_drift_amplitude=get(offset_drift, "amplitude", "torque_offset_drift.amplitude", zeros),
            ripple_amplitude=get(ripple, "amplitude", "position_ripple.amplitude", zeros),
            ripple_cycles=get(ripple, "cycles_per_rev", "position_ripple.cycles_per_rev", zeros,
                              minimum=0.0),
            joint_offset=get(data, "joint_offset", "joint_offset", zeros),
            torque_std=get(noise, "torque_std", "noise.torque_std", zeros, minimum=0.0,
                           scalar_ok=True),
            torque_std_per_rad_s=get(noise, "torque_std_per_rad_s", "noise.torque_std_per_rad_s",
                                     zeros, minimum=0.0, scalar_ok=True),
            encoder_counts_per_rev=counts,
            link_inertia=self.link_inertia(data.get("link_inertia")),
            tool_absent=tool.get("urdf_tool") == "absent",
            tool=self.rigid_body(tool["extra"], "tool.extra") if tool.get("extra") is not None else None,
            friction_drift=self.number(drift["relative_amplitude"], "friction_drift.relative_amplitude",
                                       minimum=0.0) if drift else 0.0,
            friction_drift_time_constant=self.number(drift["time_constant_s"], "friction_drift.time_constant_s",
                                                     positive=True) if drift else math.inf,
            offset_drift_period=self.number(offset_drift["period_s"], "torque_offset_drift.period_s",
                                            positive=True) if offset_drift else math.inf,
            control_rate_hz=float(rate),
            source=self.where,
        )

    def number(self, value: Any, key: str, minimum: float | None = None, positive: bool = False,
               below: float | None = None) -> float:
        """One finite number, optionally ≥ minimum, > 0 or < below."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if positive and value <= 0.0:
            raise self.fail(key, f"must be > 0, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {value!r}")
        if below is not None and value >= below:
            raise self.fail(key, f"must be < {below}, got {value!r}")
        return float(value)

    def complete(self, data: Mapping[str, Any], key: str, keys: tuple[str, str]) -> Mapping[str, Any]:
        """The section ``key`` (empty when absent); when given it must have every key of ``keys``."""
        section = self.mapping(data.get(key) or {}, key, keys)
        for name in keys:
            if section and section.get(name) is None:
                raise self.fail(f"{key}.{name}", f"is required (the section takes {list(keys)})")
        return section

    def link_inertia(self, section: Any) -> Mapping[str, LinkError] | LinkErrorDraw | None:
        """Per-link errors ``{link: {mass_scale, com_shift, inertia_scale}}`` or the generated form
        ``{seed, mass_rel, com_m, inertia_rel}``; link names are checked against the URDF later."""
        if section is None:
            return None
        if not isinstance(section, Mapping):
            raise self.fail("link_inertia", f"must be a mapping {{link: {{{', '.join(_LINK_ERROR_KEYS)}}}}} "
                                            f"or {{{', '.join(_LINK_DRAW_KEYS)}}}, got {section!r}")
        if "seed" in section:
            section = self.mapping(section, "link_inertia", _LINK_DRAW_KEYS)
            seed = section["seed"]
            if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
                raise self.fail("link_inertia.seed", f"must be an integer >= 0, got {seed!r}")
            return LinkErrorDraw(
                seed, self.number(section.get("mass_rel", 0.0), "link_inertia.mass_rel", minimum=0.0, below=1.0),
                self.number(section.get("com_m", 0.0), "link_inertia.com_m", minimum=0.0),
                self.number(section.get("inertia_rel", 0.0), "link_inertia.inertia_rel", minimum=0.0, below=1.0))
        errors = {}
        for link, entry in section.items():
            key = f"link_inertia.{link}"
            entry = self.mapping(entry, key, _LINK_ERROR_KEYS)
            scale = entry.get("inertia_scale", 1.0)
            if isinstance(scale, (int, float)) and not isinstance(scale, bool):
                scale = [scale] * 3
            scales = self._fixed(scale, 3, f"{key}.inertia_scale")
            if min(scales) <= 0.0:
                raise self.fail(f"{key}.inertia_scale", f"must be > 0, got {entry['inertia_scale']!r}")
            errors[str(link)] = LinkError(
                self.number(entry.get("mass_scale", 1.0), f"{key}.mass_scale", positive=True),
                cast(tuple[float, float, float], self._fixed(entry.get("com_shift", [0.0] * 3), 3, f"{key}.com_shift")),
                cast(tuple[float, float, float], scales))
        return MappingProxyType(errors)

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

    def rigid_body(self, section: Any, key: str) -> Payload:
        """A rigid payload or tool; its inertia must be physically possible (PSD, triangle inequality)."""
        section = self.mapping(section, key, ("mass", "com", "inertia"))
        mass = section.get("mass")
        if (isinstance(mass, bool) or not isinstance(mass, (int, float)) or not math.isfinite(mass)
                or mass <= 0):
            raise self.fail(f"{key}.mass", f"must be a number > 0 kg, got {mass!r}")
        com = self._fixed(section.get("com", [0.0, 0.0, 0.0]), 3, f"{key}.com")
        inertia = self._fixed(section.get("inertia", [0.0] * 6), 6, f"{key}.inertia")
        ixx, iyy, izz, ixy, ixz, iyz = inertia
        principal = np.linalg.eigvalsh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
        tol = 1e-12 + 1e-9 * float(np.abs(principal).max())
        if principal.min() < -tol or 2.0 * principal.max() > principal.sum() + tol:
            raise self.fail(f"{key}.inertia", f"is not a physical inertia (needs positive "
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
    ``ResidualPredictor`` of ``kvark_ros.core.estimation.observers.base``, passed to ``make_observer`` and
    ``Estimator.from_config`` as ``oracle``. τ_f is the warm friction (``friction_drift`` factor 1).

    It covers friction only. The rigid-body part of the plant (``link_inertia``, ``tool``) is ``urdf``:
    the plant's true rigid body (``kvark_ros.sim.true_model.true_urdf``), which ``Estimator.from_config``
    builds the oracle's robot model on (None: the nominal URDF). What is neither a function of q̇ nor in
    a URDF stays in the oracle's error: drive gain, armature, torque offset and ripple, the friction and
    offset drifts, the joint offset, the torque a sticking joint holds.
    """

    def __init__(self, plant: PlantSpec, n: int, urdf: str | None = None) -> None:
        self.plant = plant
        self.urdf = urdf
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


def friction_drift_factor(spec: PlantSpec, t: float) -> float:
    """Factor φ(t) on the friction torque at plant time t s since power-on: ``1 + a·e^{−t/τ}``
    (``friction_drift``): 1 + a cold, 1 once warm (t ≫ τ) and always 1 without a drift."""
    return 1.0 + spec.friction_drift * math.exp(-t / spec.friction_drift_time_constant)


def torque_offset_drift(spec: PlantSpec, t: float) -> FloatArray:
    """Drifting drive-torque offset ``d(t) = amplitude·sin(2π t / period_s)``, N·m, at plant time t s
    (``torque_offset_drift``; zeros without one)."""
    return spec.offset_drift_amplitude * math.sin(2.0 * math.pi * t / spec.offset_drift_period)


def ripple_torque(spec: PlantSpec, q: npt.ArrayLike) -> FloatArray:
    """Position-periodic drive torque ``amplitude · sin(cycles_per_rev · q)``, N·m."""
    return spec.ripple_amplitude * np.sin(spec.ripple_cycles * np.asarray(q, dtype=float))


def actuator_torque(spec: PlantSpec, q: npt.ArrayLike, tau_m: npt.ArrayLike) -> FloatArray:
    """Torque the drives apply for a command τ_m, N·m: ``drive_gain ⊙ τ_m + offset + ripple(q)``.

    Plus ``torque_offset_drift(t)`` (added by ``MujocoPlant.step``), this is the noise-free
    "measured effort" of the simulated robot.
    """
    return spec.drive_gain * np.asarray(tau_m, dtype=float) + spec.torque_offset + ripple_torque(spec, q)


def plant_effects(spec: PlantSpec, q: npt.ArrayLike, qd: npt.ArrayLike) -> FloatArray:
    """Joint torques the nominal model lacks, N·m, in the τ_f slot of the dynamics:

    ``M q̈ + C q̇ + g + plant_effects(q, q̇) = drive_gain ⊙ τ_m + τ_ext``, i.e.
    ``τ_f(q̇) − torque_offset − ripple(q)``. Armature and payload are inertia (inside M);
    the drive gain multiplies τ_m and is not a function of the state. Friction is the warm one
    (drift factor 1) and the offset drift is left out: both depend on the plant clock.
    """
    return friction_torque(spec, qd) - spec.torque_offset - ripple_torque(spec, q)


def residual_torque(spec: PlantSpec, q: npt.ArrayLike, qd: npt.ArrayLike, qdd: npt.ArrayLike,
                    tau_m: npt.ArrayLike) -> FloatArray:
    """True ``τ_m − τ_EL`` of a payload-free, contact-free motion, N·m (paper eq. 27).

    ``(1 − drive_gain) ⊙ τ_m + plant_effects(q, q̇) + armature ⊙ q̈``: what a perfect residual
    model would learn (the oracle's residual). q is the true position; a ``joint_offset`` adds
    ``g(q) − g(q + joint_offset)`` to the gap seen at the recorded position, which needs the
    robot model and is not included here; so are link inertia and tool errors (the gap of
    ``true_model.true_urdf`` to the URDF) and the drifts (see ``plant_effects``).
    """
    return ((1.0 - spec.drive_gain) * np.asarray(tau_m, dtype=float) + plant_effects(spec, q, qd)
            + spec.armature * np.asarray(qdd, dtype=float))


def effort_noise_std(spec: PlantSpec, qd: npt.ArrayLike) -> FloatArray:
    """Standard deviation of the measured-effort noise, ``torque_std + torque_std_per_rad_s·|q̇|``, N·m."""
    return spec.torque_std + spec.torque_std_per_rad_s * np.abs(np.asarray(qd, dtype=float))
