"""The estimator: robot model + observer, one call per sample.

The same object runs behind the ROS node and the bag replay, so live and offline results
are identical for identical inputs. Per sample: the input checks (``compiled.inputs``), the pinocchio
passes, then the compiled step (``compiled.step.CompiledStep``): the observer's τ̂_ext and covariance, minus the
tare offset (``kvark_ros.core.estimation.tare``), mapped to the wrench and tested for contact and collision
(``kvark_ros.core.estimation.contact``), one post-step for every observer. At run time the payload
(``set_payload``), the tare (``start_tare``/``clear_tare``) and the run-time config keys (``configure``) may change
between two samples; the filter continues. The numpy reference of a whole step is test/core/reference_estimator.py.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.augmentation import Augmentation, AugmentationError, load_augmentation
from kvark_ros.core.estimation.calibration import CALIBRATED_OBSERVER
from kvark_ros.core.estimation.compiled.inputs import (ACCEPTED, BEYOND_LIMITS, NON_FINITE, NOT_INCREASING, REPEATED,
                                                       check_sample)
from kvark_ros.core.estimation.compiled.step import CompiledStep
from kvark_ros.core.estimation.compiled.wrench import rotate
from kvark_ros.core.estimation.contact import CollisionDetector, ContactDetector
from kvark_ros.core.estimation.model_store import TrainedModel, load_model
from kvark_ros.core.estimation.observers import Observer, ResidualPredictor, make_observer
from kvark_ros.core.estimation.payload import Payload, inertia_problem
from kvark_ros.core.estimation.robot_model import RobotModel, condition_number, urdf_sha256
from kvark_ros.core.estimation.sample_limits import SampleLimits
from kvark_ros.core.estimation.tare import Tare


class _EstimateFields(NamedTuple):
    """The fields of an ``Estimate`` (a tuple: immutable and cheap to build per sample)."""

    stamp: float
    tau_ext: np.ndarray
    tau_cov: np.ndarray | None
    wrench: np.ndarray
    wrench_cov: np.ndarray | None
    contact: bool
    collision: bool
    wrench_frame: str
    ee_rotation: np.ndarray
    jacobian: np.ndarray
    weak_directions: np.ndarray


class Estimate(_EstimateFields):
    """One output sample; torque acting on the robot (docs/method.md §1.2). Its fields are a named tuple's:
    immutable and cheap to build per sample (~4 k instructions; a frozen dataclass cost 17 k).

    tau_ext: (n,) N·m, tared (``Estimator.start_tare``); tau_cov: (n, n) N²·m²; wrench: (6,) [N, N·m]
    at the end-effector frame origin, axes of ``wrench_frame`` (config ``wrench.frame``: ``base`` or
    ``end_effector``); wrench_cov: (6, 6), same axes. The covariances are ``None`` for observers that
    report no uncertainty. contact: the debounced contact flag (docs/method.md §7); collision: the
    undebounced per-joint collision flag (``kvark_ros.core.estimation.contact``). ee_rotation: (3, 3) rotation of
    the ee_frame axes in base axes, R (``v_base = R v_ee``), for ``wrench_in``. jacobian: (6, n) J in base
    axes, the one the wrench came from (``jacobian_condition``); weak_directions: (6, k) unit wrench
    directions (columns, ``wrench_frame`` axes) the joints cannot sense (σ_i < ``wrench.damping``), along
    which wrench_cov carries the damping bias for the ``wrench.prior_*`` scale (docs/method.md §1.4.1);
    k = 0 away from singular poses.
    """

    @cached_property
    def jacobian_condition(self) -> float:
        """κ = σ_max/σ_min of J (∞ for n < 6), the same in either axes; an SVD when first asked, not per sample."""
        return condition_number(self.jacobian)

    @property
    def wrench_observable(self) -> bool:
        """Whether every wrench direction is sensed by the joints (no σ_i below ``wrench.damping``)."""
        return self.weak_directions.shape[1] == 0

    def wrench_in(self, frame: str) -> np.ndarray:
        """The wrench (6,) in ``base`` or ``end_effector`` axes, same reference point (the ee_frame origin):
        a pure rotation of force and torque, ``F_base = diag(R, R) F_ee`` (exact for the damped
        pseudo-inverse too, whose ``(J Jᵀ + δ² I)`` is rotation-covariant)."""
        if frame == self.wrench_frame:
            return self.wrench
        turned = self.wrench.copy()
        rotate(self.ee_rotation.T if frame == "base" else self.ee_rotation, turned, np.zeros((6, 6)))
        return turned


class Status:
    """Outcome of the last ``Estimator.step``; also the keys of ``Estimator.counts``."""

    OK = "ok"
    WARMUP = "warm-up: first sample after start or reset"
    BAD_SHAPE = "rejected: q, qd or tau_m has the wrong length"
    NON_FINITE = "rejected: NaN, Inf or an overflowing value (|x| > 1e150) in q, qd or tau_m"
    BEYOND_LIMITS = "rejected: q, qd or tau_m beyond the URDF's limits (with margins; docs/cli.md)"
    STAMP_NOT_INCREASING = "rejected: stamp not after the previous sample (out of order or duplicate)"
    REPEATED = "rejected: q, qd and tau_m repeat the previous sample exactly while moving (a stale sample re-sent)"
    GAP_RESET = "reset: gap between samples longer than input.max_gap"
    DIVERGED_RESET = "reset: filter produced a non-finite estimate"


# The input check's codes (compiled.inputs) as the statuses they count under.
_REJECTIONS = {NON_FINITE: Status.NON_FINITE, BEYOND_LIMITS: Status.BEYOND_LIMITS,
               NOT_INCREASING: Status.STAMP_NOT_INCREASING, REPEATED: Status.REPEATED}


def model_augmentation(config: EstimatorConfig, trained: TrainedModel) -> Augmentation | None:
    """The augmentation the trained model was computed against (the model directory's copy).

    When the config names one (``model_augmentation``) it must be that same file: residuals learned
    on one model and applied on another would be silently wrong.
    """
    if not config.model_augmentation:
        return trained.augmentation
    wanted = load_augmentation(config.model_augmentation, config.joint_names)
    if trained.augmentation is None or trained.augmentation.sha256 != wanted.sha256:
        how = "without an augmentation" if trained.augmentation is None else "with another augmentation"
        raise AugmentationError(f"{config.model_augmentation}: the model in {config.model_dir} was trained {how}; "
                                "retrain with `kvark train` on this config, or set model_augmentation to ''")
    return trained.augmentation


def payload_problem(payload: Payload | None) -> str | None:
    """Why ``payload`` is not a physical rigid body (``core.estimation.payload.inertia_problem``),
    or None (also for None).

    Its 10 dynamic parameters about the flange origin: ``[m, m c, I_o]``, ``I_o = I_c + m (|c|² 𝟙 − c cᵀ)``.
    """
    if payload is None:
        return None
    m, c = float(payload.mass), np.asarray(payload.com, dtype=float)
    ixx, iyy, izz, ixy, ixz, iyz = payload.inertia
    origin = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]) + m * (c @ c * np.eye(3) - np.outer(c, c))
    return inertia_problem(np.array([m, *(m * c), origin[0, 0], origin[0, 1], origin[1, 1], origin[0, 2],
                                     origin[1, 2], origin[2, 2]]))


class Estimator:
    """Steps an observer on (stamp, q, q̇, τ_m) samples and maps τ_ext to a wrench.

    Bad samples never reach the filter: they are rejected (``step`` returns ``None``), counted
    in ``counts`` and described by ``status``. The output is always finite.

    The contact test (``contact``, a ``ContactDetector``) runs on every estimate with
    S = P + diag σ²_r(q̇) from the observer's own residual model; an observer without one falls back
    to the trained KMP with its mean as uncertainty too (docs/method.md §7), which needs ``trained``;
    with ``contact.test_covariance: reported`` and calibrated intervals, its S is the reported covariance
    (§7.2). The collision test (``collision``, a ``CollisionDetector``) uses P + diag σ²_r(q̇) in either case.
    """

    def __init__(self, config: EstimatorConfig, robot: RobotModel, observer: Observer,
                 trained: TrainedModel | None = None) -> None:
        if robot.joint_names != config.joint_names or observer.n != robot.n:
            raise ValueError("robot model, observer and config must have the same joints")
        self.config = config
        self.robot = robot
        self.observer = observer
        self.trained = trained
        # The trained static friction band widens the reported intervals at rest (core.estimation.stiction); None: not
        # identified (a model trained before it was) or filter.stiction_velocity 0.
        stiction = None if trained is None else trained.stiction
        # kvark's reported covariance is scaled by the trained interval factors (docs/method.md §4.13); None: no
        # factors (another observer, or a model trained before they were read).
        scale = trained.interval_scale if trained is not None and observer.name == CALIBRATED_OBSERVER else None
        # The contact test of an observer without a residual model adds the trained KMP's prediction (§7).
        contact_kmp = None if observer.uses_residual_model or trained is None else trained.residual
        self.contact = ContactDetector(robot.n, config.contact.confidence, config.contact.debounce)
        self.collision = CollisionDetector(config.contact.confidence, config.contact.collision_torque)
        self._compiled = CompiledStep(robot, observer, None if stiction is None else stiction.band, scale, config,
                                      self.collision.z, contact_kmp)
        self.tare = Tare(config.joint_names, config.tare.duration, config.tare.max_speed, self._compiled.offset)
        self.counts: Counter[str] = Counter()
        self.unobservable_samples = 0     # estimates with a wrench direction the joints cannot sense (§1.4.1)
        self.status = Status.WARMUP
        self._shape = (robot.n,)                              # a sample's arrays (robot.n is a pinocchio call)
        self._last_sample = np.full((3, robot.n), np.nan)     # q, q̇, τ_m of the last sample taken (repeats)
        # What a real arm can hold (the URDF's limits with margins): a sample beyond is a glitch, not data; the same
        # bounds every command that reads a bag checks (core.estimation.sample_limits).
        self.limits = SampleLimits.from_robot(robot)
        self._bounds = self.limits.bounds
        # The input check's machine code now (compiled, or loaded from numba's cache), not on the first sample taken,
        # where a cold cache stalled the node ~0.4 s and its subscription dropped joint states.
        check_sample(0.0, math.nan, np.zeros(robot.n), np.zeros(robot.n), np.zeros(robot.n),
                     np.full((3, robot.n), np.nan), self._bounds)
        self.reset()

    @classmethod
    def from_config(cls, config: EstimatorConfig, trained: TrainedModel | None = None,
                    observer: str | None = None, urdf: str | None = None,
                    oracle: ResidualPredictor | None = None) -> "Estimator":
        """Build robot model and observer from the config; ``trained`` defaults to ``config.model_dir``.

        ``urdf`` overrides ``config.urdf`` (the node passes the ``robot_description`` string);
        ``oracle`` is the true residual (the simulator's ``OracleResidual``), for the ``oracle``
        observer only, whose robot model is built on the oracle's ``urdf`` (the plant's true rigid body)
        when it has one. A non-physical ``config.payload`` raises ``ValueError``.
        """
        problem = payload_problem(config.payload)
        if problem is not None:
            raise ValueError(f"robot_model.payload: {problem}")
        name = observer or config.observer
        if name == "oracle" and urdf is None:
            urdf = getattr(oracle, "urdf", None)
        trained = trained or load_model(config.model_dir, config.joint_names,
                                        urdf_sha256(config.urdf) if urdf is None else None, baselines=(name,))
        robot = RobotModel.from_config(config, model_augmentation(config, trained), urdf)
        return cls(config, robot, make_observer(name, trained, config.filter, oracle), trained)

    def configure(self, config: EstimatorConfig) -> None:
        """Apply a config whose run-time keys changed (config_schema.KEYS ``runtime``), from the next sample.

        The estimator reads ``input.max_gap`` and ``wrench.*`` from ``config``; the observer takes
        ``config.filter`` (``Observer.configure``: a changed key that is not run-time raises
        ``ValueError`` and nothing changes), a changed ``config.payload`` goes to ``set_payload``
        (a non-physical one raises ``ValueError`` first, and nothing changes).
        """
        problem = payload_problem(config.payload)
        if problem is not None:
            raise ValueError(f"robot_model.payload: {problem}")
        self.observer.configure(config.filter)
        self.contact.configure(config.contact.confidence, config.contact.debounce)
        self.collision.configure(config.contact.confidence, config.contact.collision_torque)
        self.tare.configure(config.tare.duration, config.tare.max_speed)
        if config.payload != self.robot.payload:
            self.robot.set_payload(config.payload)
        self.config = config
        self._compiled.configure(config, self.collision.z)

    def set_payload(self, payload: Payload | None) -> None:
        """Replace the known payload at the flange (``None``: none) from the next sample; the filter continues.

        ``RobotModel.set_payload`` puts the flange link's inertia back to the model's (augmented) own and
        adds the payload, so the model is the one ``RobotModel.from_config`` builds with that payload.
        Set it at rest: while moving, the momentum jump ΔM q̇ between the two samples enters τ̂ once.
        A non-physical payload raises ``ValueError`` (the reason) and changes nothing.
        """
        problem = payload_problem(payload)
        if problem is not None:
            raise ValueError(f"payload refused: {problem}")
        self.robot.set_payload(payload)
        self.config = replace(self.config, payload=payload)

    def start_tare(self) -> None:
        """Average τ̂_ext over ``tare.duration`` s at rest, then subtract it (``kvark_ros.core.estimation.tare``);
        ``TareError`` says why it cannot start (no sample yet, moving). Progress: ``Estimator.tare.state``."""
        self.tare.start()

    def clear_tare(self) -> None:
        """Stop subtracting a tare offset (and abort an averaging)."""
        self.tare.clear()

    def reset(self) -> None:
        """Restart from the next sample (filter state, previous sample, contact and collision state forgotten;
        a tare offset stays, an averaging under way is aborted)."""
        self.observer.reset()
        self.contact.reset()
        self.collision.reset()
        self.tare.interrupt("the filter restarted")
        self._stamp: float | None = None
        self._compiled.reset()

    def continue_from(self, other: "Estimator") -> None:
        """Continue from ``other``'s state, so that swapping it for this one changes no output (model reload).

        Copies the previous sample (stamp, p, u, its q, q̇, τ_m), ``status``, the observer's filter state, the
        contact and collision detectors' state and the tare; ``counts`` stay this estimator's own.
        Raises ``ValueError`` (and changes nothing) unless both have the same joints and the same
        observer class and name, or if the observer states do not fit (``Observer.load_state``).
        """
        if self.config.joint_names != other.config.joint_names:
            raise ValueError("cannot continue from an estimator with other joints")
        mine, theirs = self.observer, other.observer
        if type(mine) is not type(theirs) or mine.name != theirs.name:
            raise ValueError(f"cannot continue observer '{mine.name}' ({type(mine).__name__}) from "
                             f"'{theirs.name}' ({type(theirs).__name__})")
        mine.load_state(theirs.state())
        self._stamp = other._stamp
        self._compiled.continue_from(other._compiled)
        self._last_sample[:] = other._last_sample
        self.status = other.status
        self.contact.continue_from(other.contact)
        self.collision.continue_from(other.collision)
        self.tare.continue_from(other.tare)

    def _reject(self, status: str) -> None:
        self.status = status
        self.counts[status] += 1

    def _accept(self, stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> float | None:
        """The input checks of ``step``: the time step dt (s) to the previous sample when the sample goes on to be
        estimated, else None (rejected and counted, or the first sample after a (re)start, which primes p and u)."""
        shape = self._shape
        if q.shape != shape or qd.shape != shape or tau_m.shape != shape:
            self._reject(Status.BAD_SHAPE)
            return None
        previous = self._stamp
        check = check_sample(stamp, math.nan if previous is None else previous, q, qd, tau_m, self._last_sample,
                             self._bounds)
        if check != ACCEPTED:
            # A stale state under a new stamp (REPEATED): stepping it would hold p for one period and then see the
            # whole catch-up as one momentum jump, which the onset detector takes for a contact (docs/method.md
            # §4.8). The next fresh sample's step spans both periods instead.
            self._reject(_REJECTIONS[check])
            return None
        gap_reset = previous is not None and stamp - previous > self.config.input.max_gap
        if gap_reset:
            self.reset()
            self._reject(Status.GAP_RESET)
            previous = None
        self._stamp = stamp
        if previous is None:
            self._prime(q, qd, tau_m)
            if not gap_reset:
                self._reject(Status.WARMUP)
            return None
        return stamp - previous

    def _prime(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        """The first sample after a (re)start: p and u only, kept for the next."""
        self._compiled.prime(q, qd, tau_m)

    def step(self, stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> Estimate | None:
        """Process one sample (arrays in ``config.joint_names`` order). ``None`` while warming up or on rejection."""
        dt = self._accept(stamp, q, qd, tau_m)
        if dt is None:
            return None
        (singular, diverged, untested, statistic, excess, tau_ext, tau_cov, wrench, wrench_cov, rotation, jacobian,
         weak) = self._compiled.step(stamp, dt, q, qd, tau_m, self.tare, self.contact.flag)
        if singular:              # wrench.damping 0 at a singular pose: J⁺ does not exist
            raise np.linalg.LinAlgError(f"wrench.damping {self.config.wrench.damping:g} at a singular pose: "
                                        "J Jᵀ + δ² I is not positive definite; set wrench.damping > 0")
        if diverged:
            return self._diverged()
        self.status = Status.OK
        self.counts[Status.OK] += 1
        contact = self.contact.flag if untested else self.contact.decide(stamp, None if math.isnan(statistic)
                                                                         else statistic)
        collision = self.collision.decide(excess)
        if weak.shape[1]:
            self.unobservable_samples += 1
        return Estimate(stamp, tau_ext, tau_cov, wrench, wrench_cov, contact, collision, self.config.wrench.frame,
                        rotation, jacobian, weak)

    def _diverged(self) -> None:
        """A non-finite estimate: restart the filter, reject the sample."""
        self.reset()
        self._reject(Status.DIVERGED_RESET)
