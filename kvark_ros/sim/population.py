"""A population of simulated robots nobody tuned for: ``draw_robot(index, seed)``.

Each robot is a Panda-, UR5- or UR10e-class arm (``ARM_CLASSES``, cycling with the index so that every class
is present in any population of three or more) with its own plant file (``kvark_ros.sim.plant``), drawn from
``numpy.random.default_rng([seed, index])``: the same (seed, index) gives the same robot on any machine.

Drawn ranges, per joint unless said otherwise; ``E`` is the joint's URDF effort limit (Panda 87/12 N·m,
UR5 150/28 N·m, UR10 330/150/54 N·m), so an effect scales with the size of its drive:

- control (and log) rate: Panda {1000, 500} Hz (FCI's 1 kHz loop, often logged at 500 Hz), UR5 {500, 125} Hz
  (e-Series RTDE / CB3), UR10 {500, 125, 100} Hz (e-Series, CB3, and a UR10e data set logged at 100 Hz);
- friction, Stribeck with stiction: Coulomb ``E × U(0.008, 0.03)`` on the Panda (0.7-2.6 N·m on the big
  joints, around Gaz et al.'s identified 0.5-1.3 N·m), ``E × U(0.02, 0.05)`` on the URs (harmonic drives
  with current-based torque: a few % of the rating, the UR5 realistic plant's 5 N·m at 3 %);
  breakaway ``static = coulomb × U(1.1, 1.5)``; Stribeck velocity ``U(0.02, 0.1)`` rad/s (the order of
  harmonic drives'); viscous ``E × U(0.001, 0.005)`` (Panda) / ``E × U(0.005, 0.02)`` (UR) N·m·s/rad;
- friction warm-up drift: relative amplitude ``U(0.05, 0.3)`` (cold grease), time constant ``U(200, 900)`` s
  (gearboxes warm up in minutes);
- armature (rotor inertia × gear ratio², what the URDF lacks), kg·m²: Panda ``U(0, 0.01)`` (link-side torque
  sensors see little of it), UR5 ``U(0.02, 0.15)`` on joints 1-3 and ``U(0.005, 0.04)`` on the wrists, UR10
  ``U(0.05, 0.3)`` and ``U(0.01, 0.06)`` (motor inertias of 1e-5-3e-5 kg·m² behind 1:101 gears);
- CAD errors on every moving link, the plant's generated ``link_inertia`` form: mass ``±U(0.05, 0.15)``,
  centre of mass within ``U(0.005, 0.02)`` m, principal moments ``±U(0.1, 0.3)`` (CAD models leave out
  cables, screws and grease; datasheet masses differ by 5-15 %);
- drive gain: ``1 ± U(0.01, 0.02)`` on the Panda (calibrated link-side torque sensors), ``1 ± U(0.03, 0.08)``
  on the URs (torque = nominal constant × motor current: torque-constant spread and temperature), sign drawn;
- torque offset ``E × U(−0.003, 0.003)`` and its drift ``E × U(0.001, 0.004)`` (sinusoid of period
  ``U(200, 900)`` s): sensor/current offsets drifting with temperature, about the realistic plants' 0.3 %;
- cogging/gear ripple ``E × U(0.001, 0.004)`` at ``cycles_per_rev`` drawn from ``RIPPLE_ORDERS`` (low orders:
  output bearing and eccentricity; 50-200: gear-tooth and 2 × ratio wave-generator orders);
- effort noise: ``torque_std`` and ``torque_std_per_rad_s`` ``U(0.02, 0.08)`` on the Panda (link-side strain
  gauges), ``U(0.06, 0.2)`` on the UR5, ``U(0.1, 0.3)`` on the UR10 (motor current, larger motors), N·m and
  N·m·s/rad; encoders 2^19 (Panda) / 2^18 (UR) counts per revolution;
- payload of the payload scene: mass ``U(0.5, 3)`` kg, a solid cylinder of radius ``U(0.03, 0.06)`` m and
  length ``U(0.05, 0.15)`` m along the flange z axis, its centre ``U(0, 0.1)`` m + half its length beyond
  the grasp point (Panda: the fingertips, 0.1 m past the flange), off-axis by up to 2 cm;
- known load of the calibration recording, motor-current arms only (``MOTOR_CURRENT_ARMS``: their drive gains are
  what free motion cannot measure): a steel cylinder of mass ``U(2, 4)`` kg (weighed: the user knows it, not its
  centre), radius 4 cm, length ``U(0.05, 0.1)`` m on the flange axis, its base ``U(0, 0.03)`` m past the flange;
  drawn from its own stream ``default_rng([seed, index, KNOWN_LOAD_STREAM])``, so the robots themselves are those
  drawn before it existed.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from kvark_ros.sim.robots import cylinder_payload, robot_setup, urdf_xml

ARM_CLASSES = ("panda", "ur5", "ur10")
RATES_HZ = {"panda": (1000.0, 500.0), "ur5": (500.0, 125.0), "ur10": (500.0, 125.0, 100.0)}
RIPPLE_ORDERS = (1, 2, 3, 4, 6, 8, 16, 32, 50, 64, 100, 101, 160, 200)
ENCODER_COUNTS = {"panda": 2**19, "ur5": 2**18, "ur10": 2**18}
GRASP_OFFSET_M = {"panda": 0.10, "ur5": 0.0, "ur10": 0.0}   # flange to where a part is held

# Documented ranges (low, high); "E" rows are shares of the joint's URDF effort limit.
COULOMB_SHARE = {"panda": (0.008, 0.03), "ur5": (0.02, 0.05), "ur10": (0.02, 0.05)}
STATIC_RATIO = (1.1, 1.5)
STRIBECK_VELOCITY = (0.02, 0.1)                  # rad/s
VISCOUS_SHARE = {"panda": (0.001, 0.005), "ur5": (0.005, 0.02), "ur10": (0.005, 0.02)}   # per rad/s
FRICTION_DRIFT = (0.05, 0.3)
DRIFT_TIME_S = (200.0, 900.0)
ARMATURE = {"panda": ((0.0, 0.01), (0.0, 0.01)), "ur5": ((0.02, 0.15), (0.005, 0.04)),
            "ur10": ((0.05, 0.3), (0.01, 0.06))}       # kg·m²: (joints 1-3, the others)
LINK_MASS_REL = (0.05, 0.15)
LINK_COM_M = (0.005, 0.02)
LINK_INERTIA_REL = (0.1, 0.3)
GAIN_ERROR = {"panda": (0.01, 0.02), "ur5": (0.03, 0.08), "ur10": (0.03, 0.08)}   # |drive_gain − 1|
OFFSET_SHARE = 0.003
OFFSET_DRIFT_SHARE = (0.001, 0.004)
OFFSET_PERIOD_S = (200.0, 900.0)
RIPPLE_SHARE = (0.001, 0.004)
NOISE = {"panda": (0.02, 0.08), "ur5": (0.06, 0.2), "ur10": (0.1, 0.3)}   # N·m and N·m·s/rad
PAYLOAD_MASS = (0.5, 3.0)
PAYLOAD_RADIUS = (0.03, 0.06)
PAYLOAD_LENGTH = (0.05, 0.15)
PAYLOAD_GAP = (0.0, 0.1)
PAYLOAD_LATERAL = 0.02
MOTOR_CURRENT_ARMS = ("ur5", "ur10")             # τ_m = gain × current (config robot_model.torque_measurement)
KNOWN_LOAD_MASS = (2.0, 4.0)                     # kg
KNOWN_LOAD_RADIUS = 0.04                         # m
KNOWN_LOAD_LENGTH = (0.05, 0.1)                  # m
KNOWN_LOAD_GAP = (0.0, 0.03)                     # m, flange to the cylinder's base
KNOWN_LOAD_STREAM = 1                            # the known load's own random stream (see the module docstring)


@dataclass(frozen=True)
class PopulationRobot:
    """One drawn robot: its arm class (``ARM_CLASSES``), the simulator's robot setup name, its control rate Hz,
    the payload mass of its payload scene (kg), the plant mapping ``load_plant`` accepts (without the payload:
    training and the contact and collision scenes carry none), the payload's plant entry, a description, and the
    known load of its calibration recording (a payload plant entry; None on arms with link-side torque sensors)."""

    index: int
    seed: int
    arm: str
    setup: str
    rate_hz: float
    payload_kg: float
    plant: dict[str, Any]
    payload: dict[str, Any]
    description: str
    known_load: dict[str, Any] | None = None

    def payload_plant(self) -> dict[str, Any]:
        """The plant mapping of the payload scene: ``plant`` carrying ``payload``."""
        return {**self.plant, "payload": self.payload}

    def known_load_plant(self) -> dict[str, Any]:
        """The plant mapping of the known-load calibration recording: ``plant`` carrying ``known_load``."""
        if self.known_load is None:
            raise ValueError(f"{self.label} has no known-load recording (link-side torque sensors)")
        return {**self.plant, "payload": self.known_load}

    @property
    def label(self) -> str:
        """``ur10 #2 (125 Hz)``: how progress lines and reports name the robot."""
        return f"{self.arm} #{self.index} ({self.rate_hz:g} Hz)"


@cache
def effort_limits(setup_name: str) -> tuple[float, ...]:
    """The URDF effort limits of the setup's joints, N·m."""
    import pinocchio as pin
    setup = robot_setup(setup_name)
    model = pin.buildModelFromXML(urdf_xml(setup.urdf))
    return tuple(float(model.effortLimit[model.joints[model.getJointId(name)].idx_v]) for name in setup.joint_names)


def _signed(rng: np.random.Generator, bounds: tuple[float, float], n: int) -> np.ndarray:
    """n magnitudes in ``bounds`` with random signs."""
    return rng.uniform(*bounds, n) * rng.choice((-1.0, 1.0), n)


def _list(values: np.ndarray, digits: int = 6) -> list[float]:
    """Plain floats for the plant mapping (YAML-friendly), rounded."""
    return [round(float(v), digits) for v in values]


def draw_robot(index: int, seed: int) -> PopulationRobot:
    """Robot ``index`` of population ``seed``: deterministic for (seed, index); ranges in the module docstring."""
    if index < 0 or seed < 0:
        raise ValueError(f"index and seed must be >= 0, got index {index}, seed {seed}")
    arm = ARM_CLASSES[index % len(ARM_CLASSES)]
    rng = np.random.default_rng([seed, index])
    effort = np.array(effort_limits(arm))
    n = len(effort)
    rate = float(rng.choice(RATES_HZ[arm]))
    coulomb = effort * rng.uniform(*COULOMB_SHARE[arm], n)
    big, small = ARMATURE[arm]
    armature = np.where(np.arange(n) < 3, rng.uniform(*big, n), rng.uniform(*small, n))
    mass = float(rng.uniform(*PAYLOAD_MASS))
    radius, length = float(rng.uniform(*PAYLOAD_RADIUS)), float(rng.uniform(*PAYLOAD_LENGTH))
    com_z = GRASP_OFFSET_M[arm] + float(rng.uniform(*PAYLOAD_GAP)) + 0.5 * length
    lateral = rng.uniform(-PAYLOAD_LATERAL, PAYLOAD_LATERAL, 2)
    body = cylinder_payload(mass, radius, length, com_z)
    noise = rng.uniform(*NOISE[arm], 2)
    plant: dict[str, Any] = {
        "friction": {"model": "stribeck", "coulomb": _list(coulomb),
                     "static": _list(coulomb * rng.uniform(*STATIC_RATIO, n)),
                     "stribeck_velocity": _list(rng.uniform(*STRIBECK_VELOCITY, n)),
                     "viscous": _list(effort * rng.uniform(*VISCOUS_SHARE[arm], n))},
        "friction_drift": {"relative_amplitude": round(float(rng.uniform(*FRICTION_DRIFT)), 4),
                           "time_constant_s": round(float(rng.uniform(*DRIFT_TIME_S)), 1)},
        "armature": _list(armature),
        "link_inertia": {"seed": int(rng.integers(0, 2**31 - 1)),
                         "mass_rel": round(float(rng.uniform(*LINK_MASS_REL)), 4),
                         "com_m": round(float(rng.uniform(*LINK_COM_M)), 4),
                         "inertia_rel": round(float(rng.uniform(*LINK_INERTIA_REL)), 4)},
        "drive_gain": _list(1.0 + _signed(rng, GAIN_ERROR[arm], n)),
        "torque_offset": _list(effort * rng.uniform(-OFFSET_SHARE, OFFSET_SHARE, n)),
        "torque_offset_drift": {"amplitude": _list(effort * rng.uniform(*OFFSET_DRIFT_SHARE, n)),
                                "period_s": round(float(rng.uniform(*OFFSET_PERIOD_S)), 1)},
        "position_ripple": {"amplitude": _list(effort * rng.uniform(*RIPPLE_SHARE, n)),
                            "cycles_per_rev": [float(c) for c in rng.choice(RIPPLE_ORDERS, n)]},
        "noise": {"torque_std": round(float(noise[0]), 4), "torque_std_per_rad_s": round(float(noise[1]), 4),
                  "encoder_counts_per_rev": ENCODER_COUNTS[arm]},
        "control_rate_hz": rate,
    }
    payload = {"mass": round(mass, 4), "com": [round(float(lateral[0]), 4), round(float(lateral[1]), 4),
                                               round(com_z, 4)],
               "inertia": _list(np.array(body.inertia), 9)}
    gains = np.array(plant["drive_gain"])
    known = _known_load(seed, index) if arm in MOTOR_CURRENT_ARMS else None
    description = (f"{arm} at {rate:g} Hz, payload {mass:.2f} kg, Coulomb {coulomb.min():.2f}-{coulomb.max():.2f} "
                   f"N·m, drive gain {gains.min():.3f}-{gains.max():.3f}, armature {armature.max():.3f} kg·m² max"
                   + ("" if known is None else f", known load {known['mass']:.2f} kg"))
    return PopulationRobot(index, seed, arm, arm, rate, round(mass, 4), plant, payload, description, known)


def _known_load(seed: int, index: int) -> dict[str, Any]:
    """The known load of robot ``index`` of population ``seed`` as a plant payload entry (module docstring)."""
    rng = np.random.default_rng([seed, index, KNOWN_LOAD_STREAM])
    mass, length = float(rng.uniform(*KNOWN_LOAD_MASS)), float(rng.uniform(*KNOWN_LOAD_LENGTH))
    body = cylinder_payload(mass, KNOWN_LOAD_RADIUS, length, float(rng.uniform(*KNOWN_LOAD_GAP)) + 0.5 * length)
    return {"mass": round(mass, 4), "com": [0.0, 0.0, round(body.com[2], 4)],
            "inertia": _list(np.array(body.inertia), 9)}


def draw_population(count: int, seed: int) -> list[PopulationRobot]:
    """Robots 0 … count−1 of population ``seed``."""
    return [draw_robot(index, seed) for index in range(count)]
