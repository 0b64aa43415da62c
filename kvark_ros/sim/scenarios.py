"""Simulated recordings with ground truth: excitation, payload, contact and collision runs.

Timing: physics at 1 kHz (``PHYSICS_DT``), the controller at the plant file's
``control_rate_hz`` (1 kHz, 500, 125 or 100 Hz), logging at ``log_rate_hz``: the control rate, at most
500 Hz (``LOG_RATE_HZ``), as a real controller logs what it runs (a 125 Hz UR writes 125 Hz). A logged sample at
stamp t_k holds what the controller saw at t_k and the command it sent then. The plant clock
(s since power-on, for the friction and torque-offset drifts) reads ``start_time + t_k``:
``run_scenario`` draws ``start_time`` per seed uniformly within the first ``SESSION_S`` after
power-on, so that recordings of one plant meet it at different temperatures, as a real robot's do,
unless it is given (the benchmark spreads its training recordings over the session that way).

Measured signals (what a real robot reports):
  position = true q + joint_offset (the plant's encoder zero error), quantised to the encoder
  resolution Δ = 2π/counts; the controller sees this position too;
  velocity = true q̇ + N(0, σ_v²), σ_v = Δ / (t_log √6): the spread of a finite difference of
  two independently quantised positions one log period apart;
  effort = drive torque ``drive_gain ⊙ τ_m + offset + ripple(q)`` + N(0, σ²),
  σ = torque_std + torque_std_per_rad_s·|q̇| (the torque noise is a sensor effect only);
  commanded effort = τ_m, the controller output.
Ground truth (what only the simulator knows): the true external joint torque
``τ_ext = Jᵀ F_ext`` summed over every external wrench, plus, for a payload the nominal model
lacks, ``τ_ext = −(ID_with_payload − ID_nominal)(q, q̇, q̈)``; and the wrist F/T wrench: what
the environment and payload apply to the robot beyond the flange, at the flange origin in flange
axes (frame_id = flange frame). Forces on links before the flange never reach that sensor. The
plant file's ``tool`` is part of the robot: neither τ_ext nor the F/T reading (tool-compensated)
includes it.
In the bag, τ_ext is the effort field of /ground_truth/external_joint_torque (position and
velocity fields zero); stamps start at 0 s.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import numpy.typing as npt
import pinocchio as pin
from tqdm import tqdm

from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io import SIMULATOR_SOURCE, CommandSeries, JointStateSeries, RecordedRun, WrenchSeries
from kvark_ros.sim.controllers import (CartesianImpedanceController, CartesianTarget,
                                       JointTrackingController)
from kvark_ros.sim.excitation import ExcitationLimits, optimise_excitation, random_trajectory
from kvark_ros.sim.mujoco_plant import PHYSICS_DT, AppliedWrench, MujocoPlant
from kvark_ros.sim.plant import PlantSpec, default_plant_path, effort_noise_std, load_plant
from kvark_ros.sim.robots import RobotSetup, robot_setup

FloatArray = npt.NDArray[np.float64]
SCENARIOS = ("excitation", "payload", "contact", "collision")
LOG_RATE_HZ = 500.0
_BLOCK = 1000                                  # physics steps per noise draw / progress update
SESSION_S = 1800.0                             # s: recordings start within half an hour of power-on
_GRAVITY = pin.Motion(np.array([0.0, 0.0, -9.81]), np.zeros(3))

Controller = Callable[[float, FloatArray, FloatArray], FloatArray]


def log_rate_hz(plant: PlantSpec) -> float:
    """Rate the simulator logs a plant at, Hz: its control rate, at most ``LOG_RATE_HZ`` (a 100 Hz robot
    writes 100 Hz bags; a 1 kHz one 500 Hz, as before)."""
    return min(plant.control_rate_hz, LOG_RATE_HZ)


class ExternalForce(Protocol):
    """Something that pushes on the robot; called every physics step with the true state."""

    def wrenches(self, t: float, plant: MujocoPlant) -> list[AppliedWrench]:
        """The wrenches (base frame) it applies at time t s."""


@dataclass(frozen=True)
class TableContact:
    """A horizontal table at ``height`` (m, base z) touching the origin of ``body``.

    Normal force: stiff spring-damper ``max(0, k·depth − d·ż)`` (N/m, N·s/m) while the frame
    origin is below the surface; tangential force: Coulomb sliding friction ``μ F_n`` against
    the sliding velocity, smoothed below ``slip_velocity`` (m/s) so the 1 ms step stays stable.
    """

    body: str
    height: float
    stiffness: float = 2.0e4
    damping: float = 300.0
    friction_coefficient: float = 0.3
    slip_velocity: float = 0.01

    def wrenches(self, t: float, plant: MujocoPlant) -> list[AppliedWrench]:
        """The table's wrench on the robot at time t s (empty when not touching)."""
        position, _ = plant.frame_pose(self.body)
        depth = self.height - position[2]
        if depth <= 0.0:
            return []
        velocity, _ = plant.frame_velocity(self.body)
        normal = max(0.0, self.stiffness * depth - self.damping * velocity[2])
        slide = velocity[:2]
        tangential = -self.friction_coefficient * normal * slide / np.hypot(np.linalg.norm(slide),
                                                                            self.slip_velocity)
        force = np.array([tangential[0], tangential[1], normal])
        return [AppliedWrench(self.body, position, force, np.zeros(3))]


@dataclass(frozen=True)
class Push:
    """A push of ``force`` (3,) N (base frame) on the centre of mass of ``body`` from ``start``
    for ``length`` s, with raised-cosine ramps of ``ramp`` s at both ends."""

    body: str
    start: float
    length: float
    force: FloatArray
    ramp: float = 0.02

    def wrenches(self, t: float, plant: MujocoPlant) -> list[AppliedWrench]:
        """The push at time t s (empty outside it)."""
        s = t - self.start
        if s <= 0.0 or s >= self.length:
            return []
        edge = min(s, self.length - s, self.ramp) / self.ramp
        scale = 0.5 - 0.5 * np.cos(np.pi * edge)
        point = plant.data.xipos[plant.body_id(self.body)].copy()
        return [AppliedWrench(self.body, point, scale * self.force, np.zeros(3))]


@dataclass(frozen=True)
class ConstantForce:
    """A constant force (3,) N, base frame, at ``offset`` (3,) m in the frame of ``body``:
    e.g. a payload's weight at its centre of mass."""

    body: str
    force: FloatArray
    offset: FloatArray

    def wrenches(self, t: float, plant: MujocoPlant) -> list[AppliedWrench]:
        """The force at time t s."""
        position, rotation = plant.frame_pose(self.body)
        return [AppliedWrench(self.body, position + rotation @ self.offset, self.force, np.zeros(3))]


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What only the simulator knows, at the log stamps: (T, n) or (T, 3) arrays.

    q, qd, qdd: true joint state (rad, rad/s, rad/s²); tau_ext: true external joint torque (N·m);
    wrench_force / wrench_torque: wrist F/T reading (N, N·m; flange origin, flange axes);
    friction: friction torque the plant applied (N·m, τ_f slot, stiction included);
    drive_torque: noise-free measured effort (N·m).
    """

    q: FloatArray
    qd: FloatArray
    qdd: FloatArray
    tau_ext: FloatArray
    wrench_force: FloatArray
    wrench_torque: FloatArray
    friction: FloatArray
    drive_torque: FloatArray


@dataclass(frozen=True, eq=False)
class SimulationOutput:
    """A simulated recording (what goes into the bag) and its ground truth.

    plant: the plant actually simulated (e.g. with the payload scenario's payload);
    wall_time: s, for the whole run including trajectory optimisation;
    start_time: the plant clock at the first sample, s since power-on.
    """

    run: RecordedRun
    truth: GroundTruth
    plant: PlantSpec
    wall_time: float
    start_time: float = 0.0

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        duration = len(self.run.joint_states.stamp) / log_rate_hz(self.plant)
        return duration / max(self.wall_time, 1e-9)


class _WrenchTruth:
    """Maps applied wrenches to τ_ext = Jᵀ F (pinocchio) and to the wrist F/T reading."""

    def __init__(self, model: RobotModel, plant: MujocoPlant) -> None:
        self.model = model
        self.plant = plant
        self.flange = model.flange_frame_id
        self._sensed: dict[str, bool] = {}

    def __call__(self, q: FloatArray, wrenches: Sequence[AppliedWrench]) -> tuple[FloatArray, FloatArray]:
        """(τ_ext (n,), F/T (6,) force then torque) for wrenches applied at configuration q."""
        tau, sensor = np.zeros(self.model.n), np.zeros(6)
        if not wrenches:
            return tau, sensor
        mdl, data = self.model.model, self.model.data
        pin.framesForwardKinematics(mdl, data, q)
        for wrench in wrenches:
            frame = mdl.getFrameId(wrench.body)
            jac = pin.computeFrameJacobian(mdl, data, q, frame, pin.LOCAL_WORLD_ALIGNED)
            origin = data.oMf[frame].translation
            moment = wrench.torque + np.cross(wrench.point - origin, wrench.force)
            tau += jac[:3].T @ wrench.force + jac[3:].T @ moment
            if self._sensed.setdefault(wrench.body, self.plant.in_flange_subtree(wrench.body)):
                pose = data.oMf[self.flange]
                moment = wrench.torque + np.cross(wrench.point - pose.translation, wrench.force)
                sensor += np.concatenate([pose.rotation.T @ wrench.force, pose.rotation.T @ moment])
        return tau, sensor


def payload_truth(nominal: RobotModel, loaded: RobotModel, q: FloatArray, qd: FloatArray,
                  qdd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """External joint torque (T, n) and wrist wrench (T, 6) of a payload the nominal model lacks.

    ``loaded`` is the nominal model with the payload. ``τ_ext = −(ID_loaded − ID_nominal)(q, q̇, q̈)``;
    the wrench is what the payload applies to the flange, ``−(I a_g + v ×* I v)`` (Newton–Euler)
    with the flange's spatial velocity v and acceleration a_g (gravity included) in flange axes,
    force first.
    """
    if loaded.payload is None:
        raise ValueError("payload_truth needs a model with a payload")
    inertia = loaded.payload.to_pinocchio()
    mdl, data, flange = nominal.model, nominal.data, nominal.flange_frame_id
    tau, wrench = np.zeros_like(q), np.zeros((q.shape[0], 6))
    for k in range(q.shape[0]):
        tau[k] = nominal.inverse_dynamics(q[k], qd[k], qdd[k]) - loaded.inverse_dynamics(q[k], qd[k], qdd[k])
        pin.forwardKinematics(mdl, data, q[k], qd[k], qdd[k])
        pin.updateFramePlacement(mdl, data, flange)
        v = pin.getFrameVelocity(mdl, data, flange, pin.LOCAL)
        a_g = pin.getFrameAcceleration(mdl, data, flange, pin.LOCAL) - data.oMf[flange].actInv(_GRAVITY)
        force = inertia * a_g + v.cross(inertia * v)
        wrench[k] = -np.concatenate([force.linear, force.angular])
    return tau, wrench


def run_simulation(setup: RobotSetup, plant: PlantSpec, controller: Controller, duration: float,
                   start: FloatArray, rng: np.random.Generator, forces: Sequence[ExternalForce] = (),
                   progress: bool | None = None, label: str = "", start_time: float = 0.0) -> SimulationOutput:
    """Simulate ``duration`` s from rest at ``start`` (rad) and record it (see module docstring).

    ``start`` is the position the encoders read at t = 0: the arm starts at ``start −
    joint_offset``, so a controller tracking a trajectory that begins at ``start`` starts on it.

    controller(t, q_measured, q̇_measured) → τ_m runs at the plant's control rate; ``forces``
    act every physics step; ``rng`` draws the sensor noise. progress: True/False shows/hides a
    tqdm bar, None shows it on a terminal only; either way it appears only for runs that take
    more than a second of wall time. start_time: the plant clock at t = 0, s since power-on.
    """
    wall_start = time.perf_counter()
    n, names = setup.n, setup.joint_names
    log_rate = log_rate_hz(plant)
    steps_per_log = int(round(1.0 / (log_rate * PHYSICS_DT)))
    logs = int(round(duration * log_rate))
    if logs < 2:
        raise ValueError(f"duration {duration} s is shorter than two log periods")
    steps = logs * steps_per_log
    control_every = int(round(1.0 / (plant.control_rate_hz * PHYSICS_DT)))
    resolution = plant.encoder_resolution
    velocity_std = resolution / (np.sqrt(6.0) / log_rate)
    sim = MujocoPlant(setup, plant)
    sim.reset(np.asarray(start, dtype=float) - plant.joint_offset, time=start_time)
    nominal = setup.nominal_model()
    wrench_truth = _WrenchTruth(nominal, sim)

    columns = ("q", "qd", "qdd", "q_meas", "qd_meas", "tau_m", "drive", "friction", "tau_ext")
    rec = {key: np.zeros((logs, n)) for key in columns}
    sensor = np.zeros((logs, 6))
    tau_m = np.zeros(n)
    bar = tqdm(total=round(duration, 3), unit="sim s", desc=label or setup.name,
               disable=None if progress is None else not progress, leave=False, delay=1.0)
    for k in range(steps):
        if k % _BLOCK == 0:
            velocity_noise = rng.standard_normal((_BLOCK, n)) * velocity_std
            if k:
                bar.update(_BLOCK * PHYSICS_DT)
        t = k * PHYSICS_DT
        q, qd = sim.q, sim.qd
        q_read = q + plant.joint_offset
        q_meas = q_read if resolution == 0.0 else resolution * np.round(q_read / resolution)
        qd_meas = qd + velocity_noise[k % _BLOCK]
        if k % control_every == 0:
            tau_m = controller(t, q_meas, qd_meas)
        wrenches = [w for force in forces for w in force.wrenches(t, sim)]
        sim.apply(wrenches)
        drive, friction, qdd = sim.step(tau_m)
        if k % steps_per_log == 0:
            i = k // steps_per_log
            rec["tau_ext"][i], sensor[i] = wrench_truth(q, wrenches)
            for key, value in zip(columns[:-1], (q, qd, qdd, q_meas, qd_meas, tau_m, drive, friction)):
                rec[key][i] = value
    bar.update(max(0.0, round(duration - bar.n, 3)))
    bar.close()

    if plant.payload is not None:
        tau_payload, wrench_payload = payload_truth(nominal, setup.nominal_model(plant.payload),
                                                    rec["q"], rec["qd"], rec["qdd"])
        rec["tau_ext"] += tau_payload
        sensor += wrench_payload
    effort = rec["drive"] + effort_noise_std(plant, rec["qd"]) * rng.standard_normal((logs, n))
    stamp = np.arange(logs, dtype=np.int64) * int(round(1e9 / log_rate)) / 1e9
    zeros = np.zeros((logs, n))
    run = RecordedRun(
        joint_states=JointStateSeries(stamp, names, rec["q_meas"], rec["qd_meas"], effort),
        commands=CommandSeries(stamp, rec["tau_m"].copy()),
        wrench=WrenchSeries(stamp, setup.flange_frame, sensor[:, :3].copy(), sensor[:, 3:].copy()),
        external_torque=JointStateSeries(stamp, names, zeros, zeros, rec["tau_ext"].copy()),
        source=f"{SIMULATOR_SOURCE}: {label or setup.name}",
    )
    truth = GroundTruth(rec["q"], rec["qd"], rec["qdd"], rec["tau_ext"], sensor[:, :3].copy(),
                        sensor[:, 3:].copy(), rec["friction"], rec["drive"])
    return SimulationOutput(run, truth, plant, time.perf_counter() - wall_start, start_time)


def _quintic(s: float) -> float:
    """Minimum-jerk time scaling on [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _quintic_rate(s: float) -> float:
    """d/ds of ``_quintic``."""
    s = min(max(s, 0.0), 1.0)
    return 30.0 * s**2 * (1.0 - s) ** 2


@dataclass(frozen=True)
class SquarePath:
    """Polishing reference (paper v2, exp. 2): descend to ``depth`` m below the table surface,
    then trace a square of ``side`` m about the touchdown point at ``speed`` m/s (minimum-jerk per
    edge), holding the start orientation. The impedance spring then presses with about
    ``K_z · depth`` N."""

    start: FloatArray
    rotation: FloatArray
    table_height: float
    depth: float
    side: float = 0.12
    speed: float = 0.05
    approach_time: float = 1.5

    def _waypoints(self) -> tuple[FloatArray, FloatArray]:
        """Waypoints (6, 2) m: the touchdown point (centre), then the square's corners back to the
        first one; durations (5,) s of the lead-in edge and the four sides."""
        h = 0.5 * self.side
        corners = self.start[:2] + np.array([[0.0, 0.0], [-h, -h], [h, -h], [h, h], [-h, h], [-h, -h]])
        lengths = np.linalg.norm(np.diff(corners, axis=0), axis=1)
        return corners, lengths / self.speed

    def __call__(self, t: float) -> CartesianTarget:
        """Target pose and velocity at time t s."""
        bottom = self.table_height - self.depth
        if t < self.approach_time:
            s = t / self.approach_time
            z = self.start[2] + (bottom - self.start[2]) * _quintic(s)
            vz = (bottom - self.start[2]) * _quintic_rate(s) / self.approach_time
            return CartesianTarget(np.array([self.start[0], self.start[1], z]), self.rotation,
                                   np.array([0.0, 0.0, vz]))
        corners, times = self._waypoints()
        t -= self.approach_time
        edge = 0
        if t >= times[0]:                     # after the lead-in, loop over the four sides
            t = (t - times[0]) % times[1:].sum()
            edge = 1
            while t >= times[edge]:
                t -= times[edge]
                edge += 1
        s = t / times[edge]
        delta = corners[edge + 1] - corners[edge]
        xy = corners[edge] + delta * _quintic(s)
        vxy = delta * _quintic_rate(s) / times[edge]
        return CartesianTarget(np.array([xy[0], xy[1], bottom]), self.rotation,
                               np.array([vxy[0], vxy[1], 0.0]))


def _resolve_plant(setup: RobotSetup, plant: PlantSpec | str | os.PathLike[str] | None) -> PlantSpec:
    """A PlantSpec from a spec, a plant-file path, or None (the robot's default plant file)."""
    if isinstance(plant, PlantSpec):
        if plant.n != setup.n:
            raise ValueError(f"plant is for {plant.n} joints, {setup.name} has {setup.n}")
        return plant
    return load_plant(default_plant_path(setup.name) if plant is None else plant, setup.n)


def run_scenario(robot: str, scenario: str, seed: int = 1, duration: float = 10.0,
                 plant: PlantSpec | str | os.PathLike[str] | None = None,
                 progress: bool | None = None, start_time: float | None = None,
                 motion_seed: int | None = None) -> SimulationOutput:
    """Simulate one scenario and return the recording with its ground truth.

    excitation: an optimised eq.-24/25 trajectory under joint tracking control;
    payload: another optimised trajectory carrying a payload the nominal model lacks (the plant
        file's payload, else the robot's default 2 kg part);
    contact: Cartesian impedance polishing square on a table, ~15 N normal force;
    collision: plain joint-space motion with a 20-40 N, 0.2 s push on a link every ~5 s.
    plant: a PlantSpec, a plant-file path, or None for the robot's default plant file
    (``kvark_ros/sim/plants/<robot>_default.yaml``). Deterministic for a seed, which also sets
    the plant clock at the start (module docstring) unless ``start_time`` (s since power-on, ≥ 0) is given.
    ``motion_seed``: the seed whose motion to repeat (the trajectory of this scenario and duration under that seed),
    with this seed's noise and clock: a run carrying a known load along the same trajectory as an unloaded one, as a
    drive-gain calibration records them (Mamedov et al. 2020).
    """
    wall_start = time.perf_counter()
    setup = robot_setup(robot)
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    if not np.isfinite(duration) or duration <= 0.0:
        raise ValueError(f"duration must be > 0 s, got {duration}")
    if start_time is not None and not (np.isfinite(start_time) and start_time >= 0.0):
        raise ValueError(f"start_time must be a finite time ≥ 0 s since power-on, got {start_time}")
    spec = _resolve_plant(setup, plant)
    trajectory_seed, scenario_seed, noise_seed, clock_seed = np.random.SeedSequence(
        [seed, SCENARIOS.index(scenario)]).spawn(4)
    if motion_seed is not None:
        trajectory_seed = np.random.SeedSequence([motion_seed, SCENARIOS.index(scenario)]).spawn(4)[0]
    drawn = float(np.random.default_rng(clock_seed).uniform(0.0, SESSION_S))
    start_time = drawn if start_time is None else float(start_time)
    scenario_rng = np.random.default_rng(scenario_seed)
    nominal = setup.nominal_model()
    limits = ExcitationLimits.for_robot(setup)
    forces: list[ExternalForce] = []
    controller: Controller
    if scenario in ("excitation", "payload"):
        if scenario == "payload" and spec.payload is None:
            spec = replace(spec, payload=setup.payload)
        trajectory = optimise_excitation(limits, duration, np.random.default_rng(trajectory_seed)).trajectory
        controller = JointTrackingController(nominal, trajectory, setup.kp, setup.kd)
        start = trajectory(0.0)[0]
    elif scenario == "collision":
        trajectory = random_trajectory(limits, duration, np.random.default_rng(trajectory_seed))
        controller = JointTrackingController(nominal, trajectory, setup.kp, setup.kd)
        start = trajectory(0.0)[0]
        forces.extend(_pushes(setup.push_link, duration, scenario_rng))
    else:
        start = setup.home_array()
        controller, table = _polishing(setup, nominal, start)
        forces.append(table)
    output = run_simulation(setup, spec, controller, duration, start, np.random.default_rng(noise_seed),
                            forces, progress, label=f"{robot} {scenario}", start_time=start_time)
    return replace(output, wall_time=time.perf_counter() - wall_start)


def simulate(robot: str, scenario: str, seed: int = 1, duration: float = 10.0,
             plant: PlantSpec | str | os.PathLike[str] | None = None,
             progress: bool | None = None, start_time: float | None = None,
             motion_seed: int | None = None) -> RecordedRun:
    """The recording of ``run_scenario`` (what a bag holds); same arguments."""
    return run_scenario(robot, scenario, seed, duration, plant, progress, start_time, motion_seed).run


def _pushes(link: str, duration: float, rng: np.random.Generator) -> list[Push]:
    """One horizontal 20-40 N, 0.2 s push per ~5 s segment, at a random time in its middle."""
    count = max(1, int(round(duration / 5.0)))
    segment = duration / count
    pushes = []
    for i in range(count):
        start = segment * (i + rng.uniform(0.3, 0.6))
        angle = rng.uniform(0.0, 2.0 * np.pi)
        magnitude = rng.uniform(20.0, 40.0)
        force = magnitude * np.array([np.cos(angle), np.sin(angle), 0.0])
        pushes.append(Push(link, start, min(0.2, 0.5 * segment), force))
    return pushes


def _polishing(setup: RobotSetup, nominal: RobotModel,
               home: FloatArray) -> tuple[CartesianImpedanceController, TableContact]:
    """Impedance controller tracing a square on a table 3 cm below the TCP at ``home``,
    pressing with ~15 N (K_z · depth)."""
    nominal.jacobian(home, "base")
    pin.updateFramePlacement(nominal.model, nominal.data, nominal.ee_frame_id)
    pose = nominal.data.oMf[nominal.ee_frame_id]
    stiffness = np.array([800.0, 800.0, 800.0, 10.0, 10.0, 10.0])   # N/m, N·m/rad
    damping = np.array([60.0, 60.0, 60.0, 3.0, 3.0, 3.0])            # N·s/m, N·m·s/rad
    normal_force = 15.0                                               # N
    table_height = float(pose.translation[2]) - 0.03
    path = SquarePath(pose.translation.copy(), pose.rotation.copy(), table_height,
                      depth=normal_force / stiffness[2])
    controller = CartesianImpedanceController(nominal, path, stiffness, damping, home,
                                              nullspace_stiffness=5.0, nullspace_damping=0.5)
    return controller, TableContact(setup.ee_frame, table_height)
