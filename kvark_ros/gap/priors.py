"""Physical priors of ``kvark diagnose``: a plausible range for every effect, scaled to the robot (docs/method.md §8.6).

Every bound is a share of something the URDF states (a joint's effort limit τ_max and velocity limit q̇_max, a link's
mass and first moments) times a width that follows how τ_m is measured (``robot_model.torque_measurement``):

* ``link_torque_sensor`` (Panda, KUKA iiwa): strain gauges behind the gear measure the link-side torque; calibrated
  gains within ~2 %, the rotor and the gear's own inertia sit before the sensor (a quarter of the motor's armature
  bound: output bearing and flexspline only);
* ``motor_current`` (UR: τ = k_t N i): the torque constant and the gear efficiency change with temperature and
  load (±10 %), offsets and low-order ripple of the current loop, the rotor's inertia and the gear's friction are
  all in τ_m;
* ``commanded_effort``: what a controller asked for, with whatever the drive's inner loops add (widest).

Per joint j, with s the measurement's share (``MEASUREMENT_WIDTHS``):

* ``drive_gain``       |1 − g| ≤ s_gain (2 / 10 / 20 %), or ``--max-gain-error``;
* ``torque_offset``    |o| ≤ s_offset τ_max (2 / 3 / 5 %): sensor zero drift, current-sensor offsets;
* ``position_ripple``  |a|, |b| ≤ s_ripple τ_max (1 / 2 / 5 %): a ripple of k ≤ 100 cycles per joint revolution
  comes from the gear's output stage (motor cogging, 1-2 % of the motor's rated torque, repeats N·slots times a
  joint revolution and is filtered out), so low orders are small;
* ``coulomb_friction`` F_c ≤ s_friction τ_max, ``stribeck_friction`` F_s − F_c ≤ s_friction τ_max (10 / 20 / 30 %):
  harmonic-drive efficiencies of 70-85 % at rated torque and 50-70 % at light load and low temperature (the gear's
  friction is in a current-based τ_m, mostly not in a link-side sensor's); ``viscous_friction``
  F_v ≤ s_friction τ_max / q̇_max (the viscous torque at full speed within the same share);
* ``armature``         I_a ≤ c τ_max t_a / q̇_max, t_a = ``ACCELERATION_TIME`` (c = 0.25 / 1 / 2): the reflected rotor
  inertia N² J_m of a motor whose unloaded rotor reaches its top speed ω_m = N q̇_max under its peak torque
  τ_max / N in t_a = J_m ω_m N / τ_max = I_a q̇_max / τ_max (the gear ratio cancels); servo motors' datasheets give
  5-20 ms (e.g. maxon EC 45 flat 18 ms, Kollmorgen AKM2 6 ms), 30 ms with the gear's own inertia;
* ``joint_offset``     |δ| ≤ 1° (``--max-joint-offset``): absolute encoders, factory calibrated;
* ``payload``          mass ≤ the largest point mass at the flange every gravity-loaded joint can hold over its own
  arm's gravity torque within τ_max, over sampled postures (``payload_mass_limit``): the rated payload the effort
  limits imply (UR10e ≈ 16 kg for 12.5 kg rated);
* ``link_inertia``     |Δm| ≤ ``LINK_MASS_SHARE`` m, |Δ(m c)| ≤ ``LINK_MASS_SHARE`` |m c| + m ``LINK_COM_SHIFT``
  per link (CAD masses miss cables, covers and grease by tens of per cent, CoMs by centimetres); the second
  moments keep their Gaussian prior toward the URDF and physical consistency.

Beyond a prior lies what the data may still want (``admissible.beyond_priors`` offers it, with the flag); beyond
physics lies what no drive does (``physics``: |1 − g| ≤ ``PHYSICAL_GAIN_ERROR``, an offset, ripple or friction within
the joint's effort limit): that is never offered as an explanation.

A URDF without an effort limit (0 or ∞) leaves the effort-scaled bounds of that joint open, and says so.
``--prior EFFECT=FACTOR`` scales one effect's bounds (gains and offsets: ``--max-gain-error``, ``--max-joint-offset``).
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Mapping

import numpy as np
import pinocchio as pin

from kvark_ros.core.config_schema import TORQUE_MEASUREMENTS
from kvark_ros.core.effect_catalog import MEASUREMENT_WIDTHS
from kvark_ros.core.estimation.robot_model import RobotModel

if TYPE_CHECKING:
    from kvark_ros.gap.effects import Priors

assert set(MEASUREMENT_WIDTHS) == set(TORQUE_MEASUREMENTS)
ACCELERATION_TIME = 0.03     # s, unloaded rotor from rest to top speed under peak torque (armature bound)
DEFAULT_SPEED = math.pi      # rad/s, q̇_max of a joint whose URDF gives none
LINK_MASS_SHARE = 0.5        # link_inertia: |Δm| ≤ 50 % of the link's URDF mass
LINK_COM_SHIFT = 0.05        # m, and its centre of mass by 5 cm
POSTURES = 256               # sampled postures of the payload bound
# The flag that widens each effect's prior (the others: --prior EFFECT=FACTOR).
FLAGS = {"drive_gain": "--max-gain-error", "joint_offset": "--max-joint-offset"}
FAR_BEYOND = 3.0             # a value more than 3× its prior's bound is far beyond it: the report says so
# Physics, not priors: a torque constant off by half is a wrong drive configuration (gear ratio, units), not a
# calibration error, and a gain near zero is a joint without torque; an offset, ripple or friction larger than the
# joint's whole effort limit cannot be carried by its drive.
PHYSICAL_GAIN_ERROR = 0.5
PHYSICAL_EFFORT_SHARE = 1.0
# Units of a bound, for the report.
UNITS = {"drive_gain": "(1 − g, absolute)", "torque_offset": "N·m", "position_ripple": "N·m (each of sin, cos)",
         "coulomb_friction": "N·m", "stribeck_friction": "N·m", "viscous_friction": "N·m·s/rad",
         "armature": "kg·m²", "joint_offset": "rad", "payload": "kg (mass)",
         "link_inertia": "kg (mass), kg·m (first moments)"}


def _limits(robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    """(τ_max, q̇_max) per joint from the URDF; τ_max ∞ where it gives none, q̇_max ``DEFAULT_SPEED``."""
    effort = np.asarray(robot.model.effortLimit, dtype=float)[:robot.n]
    speed = np.asarray(robot.model.velocityLimit, dtype=float)[:robot.n]
    effort = np.where(np.isfinite(effort) & (effort > 0.0), effort, np.inf)
    speed = np.where(np.isfinite(speed) & (speed > 0.0), speed, DEFAULT_SPEED)
    return effort, speed


def payload_mass_limit(robot: RobotModel) -> float:
    """Largest point mass at the flange every joint holds within its effort limit over its own arm's gravity, over
    ``POSTURES`` sampled postures (seeded) and the zero posture; ∞ without effort limits."""
    model, data = robot.model, robot.data
    effort, _ = _limits(robot)
    low = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.pi)
    high = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.pi)
    rng = np.random.default_rng(0)
    postures = [pin.neutral(model)] + [rng.uniform(low, high) for _ in range(POSTURES)]
    arm = np.zeros(model.nv)
    per_kg = np.zeros(model.nv)
    for q in postures:
        arm = np.maximum(arm, np.abs(pin.computeGeneralizedGravity(model, data, q)))
        jac = pin.computeFrameJacobian(model, data, q, robot.flange_frame_id, pin.LOCAL_WORLD_ALIGNED)
        per_kg = np.maximum(per_kg, np.abs(jac[:3].T @ np.array([0.0, 0.0, 9.81])))
    loaded = per_kg[:robot.n] > 1e-3 * max(float(per_kg.max()), 1e-300)
    room = (effort - arm[:robot.n])[loaded] / per_kg[:robot.n][loaded]
    return float(max(np.min(room), 0.0)) if room.size else math.inf


def _joint_bounds(name: str, widths: Mapping[str, float], effort: np.ndarray, speed: np.ndarray) -> tuple:
    """(bound per joint, source) of a per-joint effect scaled by the effort limit."""
    if name == "torque_offset":
        return widths["offset"] * effort, f"{widths['offset']:.0%} of the URDF effort limit"
    if name == "position_ripple":
        return widths["ripple"] * effort, f"{widths['ripple']:.0%} of the URDF effort limit (gear output stage)"
    if name in ("coulomb_friction", "stribeck_friction"):
        return widths["friction"] * effort, f"{widths['friction']:.0%} of the URDF effort limit"
    if name == "viscous_friction":
        return (widths["friction"] * effort / speed,
                f"{widths['friction']:.0%} of the URDF effort limit at the URDF velocity limit")
    if name == "armature":
        time = widths["armature"] * ACCELERATION_TIME
        return (effort * time / speed, f"effort limit × {time * 1e3:.1f} ms / velocity limit (reflected rotor "
                                       "inertia of a motor reaching top speed under peak torque)")
    raise KeyError(name)


def link_bounds(robot: RobotModel) -> np.ndarray:
    """|Δπ| bounds (10 per link before the flange's): mass and first moments (``LINK_MASS_SHARE``,
    ``LINK_COM_SHIFT``), second moments ∞."""
    jid = robot.model.frames[robot.flange_frame_id].parentJoint
    bounds = []
    for i in range(1, jid):
        pi = robot.model.inertias[i].toDynamicParameters()
        m = max(float(pi[0]), 0.1)
        bounds.append(np.concatenate([[LINK_MASS_SHARE * m],
                                      LINK_MASS_SHARE * np.abs(pi[1:4]) + m * LINK_COM_SHIFT, np.full(6, np.inf)]))
    return np.concatenate(bounds) if bounds else np.zeros(0)


def robot_priors(robot: RobotModel, priors: Priors) -> Priors:
    """``priors`` with every effect's bounds (``limits``) and their sources (``sources``) derived from ``robot``'s
    URDF and ``priors.torque_measurement``, each scaled by its ``--prior`` factor."""
    if priors.torque_measurement not in MEASUREMENT_WIDTHS:
        raise ValueError(f"unknown torque measurement {priors.torque_measurement!r}; known: "
                         f"{', '.join(TORQUE_MEASUREMENTS)}")
    widths = MEASUREMENT_WIDTHS[priors.torque_measurement]
    effort, speed = _limits(robot)
    how = f"τ_m is {priors.torque_measurement}"
    gain_source = ("--max-gain-error" if priors.max_gain_error is not None
                   else f"{widths['gain']:.0%} for {priors.torque_measurement}")
    limits = {"drive_gain": np.full(robot.n, priors.gain_bound),
              "joint_offset": np.full(robot.n, priors.max_joint_offset)}
    sources = {"drive_gain": gain_source, "joint_offset": "absolute encoders (--max-joint-offset)"}
    urdf = f"τ_max {', '.join(f'{e:g}' for e in effort)} N·m"
    for name in ("coulomb_friction", "viscous_friction", "stribeck_friction", "armature", "torque_offset",
                 "position_ripple"):
        limits[name], text = _joint_bounds(name, widths, effort, speed)
        velocity = f", q̇_max {', '.join(f'{v:.3g}' for v in speed)} rad/s" if name in ("viscous_friction",
                                                                                     "armature") else ""
        sources[name] = f"{text} ({urdf}{velocity}); {how}"
    limits["payload"] = np.array([payload_mass_limit(robot)])
    sources["payload"] = "point mass at the flange the effort limits hold over the arm's own gravity"
    limits["link_inertia"] = link_bounds(robot)
    sources["link_inertia"] = (f"±{LINK_MASS_SHARE:.0%} of each link's URDF mass, first moments ±{LINK_MASS_SHARE:.0%} "
                               f"+ m·{LINK_COM_SHIFT * 100:.0f} cm")
    for name, factor in priors.scale:
        limits[name] = limits[name] * factor
        sources[name] += f", × {factor:g} (--prior)"
    physics = {"drive_gain": np.full(robot.n, PHYSICAL_GAIN_ERROR),
               **{name: PHYSICAL_EFFORT_SHARE * effort for name in ("torque_offset", "position_ripple",
                                                                   "coulomb_friction", "stribeck_friction")},
               "viscous_friction": PHYSICAL_EFFORT_SHARE * effort / speed}
    if not np.all(np.isfinite(effort)):
        missing = ", ".join(robot.joint_names[j] for j in np.flatnonzero(~np.isfinite(effort)))
        for name in ("coulomb_friction", "viscous_friction", "stribeck_friction", "armature", "torque_offset",
                     "position_ripple"):
            sources[name] += f" (no effort limit in the URDF for {missing}: open there)"
    return replace(priors, limits=limits, sources=sources, physics=physics)


def suggested_flag(name: str, wanted: float, bound: float) -> str:
    """The flag that would let ``name`` reach ``wanted`` (|θ| of the parameter beyond its ``bound``), with 10 %
    room, rounded up."""
    if name == "drive_gain":
        return f"--max-gain-error {math.ceil(wanted * 1.1 / 0.05) * 0.05:.2f}"
    if name == "joint_offset":
        return f"--max-joint-offset {math.ceil(math.degrees(wanted) * 1.1 / 0.5) * 0.5:g}"
    return f"--prior {name}={math.ceil(wanted / bound * 1.1 / 0.5) * 0.5:g}"
