"""The estimator: robot model + observer, one call per sample.

The same object runs behind the ROS node and the bag replay, so live and offline results
are identical for identical inputs. Per sample: the observer's τ̂_ext, minus the tare offset
(``kvark_ros.core.estimation.tare``), mapped to the wrench and tested for contact and collision
(``kvark_ros.core.estimation.contact``). At run time the payload (``set_payload``), the tare
(``start_tare``/``clear_tare``) and the run-time config keys (``configure``) may change between
two samples; the filter continues.

With a momentum-form K-VARK filter (a ``KVARKKernelFilter``) everything of a step but the pinocchio passes runs as one
compiled kernel (``kvark_ros.core.estimation.step_kernel``); the numpy code below is the reference it is tested against.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from kvark_ros.core.estimation.augmentation import Augmentation, AugmentationError, load_augmentation
from kvark_ros.core.estimation.calibration import CALIBRATED_OBSERVER
from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.contact import CollisionDetector, ContactDetector, contact_covariance
from kvark_ros.core.estimation.model_store import TrainedModel, load_model
from kvark_ros.core.estimation.observers import Observer, ResidualPredictor, make_observer
from kvark_ros.core.estimation.payload import Payload, inertia_problem
from kvark_ros.core.estimation.robot_model import RobotModel, condition_number, urdf_sha256
from kvark_ros.core.estimation.input_kernels import repeated_sample
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
        return rotate_wrench(self.ee_rotation if frame == "base" else self.ee_rotation.T, self.wrench)[0]


def rotate_wrench(rotation: np.ndarray, wrench: np.ndarray, cov: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """A wrench (6,) or wrench directions (6, k), and a covariance (6, 6) or None, in other axes, same
    reference point: ``F' = B F``, ``Σ' = B Σ Bᵀ``, ``B = diag(R, R)``, ``R`` (3, 3) the rotation to the new axes."""
    turned = np.concatenate((rotation @ wrench[:3], rotation @ wrench[3:]))
    if cov is None:
        return turned, None
    block = np.kron(np.eye(2), rotation)
    turned_cov = block @ cov @ block.T
    return turned, 0.5 * (turned_cov + turned_cov.T)


class Status:
    """Outcome of the last ``Estimator.step``; also the keys of ``Estimator.counts``."""

    OK = "ok"
    WARMUP = "warm-up: first sample after start or reset"
    BAD_SHAPE = "rejected: q, qd or tau_m has the wrong length"
    NON_FINITE = "rejected: NaN, Inf or an overflowing value (|x| > 1e150) in q, qd or tau_m"
    STAMP_NOT_INCREASING = "rejected: stamp not after the previous sample (out of order or duplicate)"
    REPEATED = "rejected: q, qd and tau_m repeat the previous sample exactly while moving (a stale sample re-sent)"
    GAP_RESET = "reset: gap between samples longer than input.max_gap"
    DIVERGED_RESET = "reset: filter produced a non-finite estimate"


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
        self._contact_residual = None if observer.uses_residual_model or trained is None else trained.residual
        # The trained static friction band widens the reported intervals at rest (core.estimation.stiction); None: not
        # identified (a model trained before it was) or filter.stiction_velocity 0.
        self._stiction = None if trained is None else trained.stiction
        # kvark's reported covariance is scaled by the trained interval factors (docs/method.md §4.13); None: no
        # factors (another observer, or a model trained before they were read).
        self._interval_scale = (trained.interval_scale if trained is not None and observer.name == CALIBRATED_OBSERVER
                                else None)
        # Pose inputs of the residual model in use (observer's or contact test's): g(q) costs a pinocchio pass.
        self._needs = observer.needs | frozenset(getattr(self._contact_residual, "needs", ()))
        self.contact = ContactDetector(robot.n, config.contact.confidence, config.contact.debounce)
        self.collision = CollisionDetector(config.contact.confidence, config.contact.collision_torque)
        self.tare = Tare(config.joint_names, config.tare.duration, config.tare.max_speed)
        self.counts: Counter[str] = Counter()
        self.unobservable_samples = 0     # estimates with a wrench direction the joints cannot sense (§1.4.1)
        self.status = Status.WARMUP
        self._p_prev, self._u_prev = np.zeros(robot.n), np.zeros(robot.n)
        self._last_sample = np.full((3, robot.n), np.nan)     # q, q̇, τ_m of the last sample taken (repeats)
        # The repeat check's machine code now (compiled, or loaded from numba's cache), not on the first sample taken,
        # where a cold cache stalled the node ~0.4 s and its subscription dropped joint states.
        repeated_sample(0.0, self._p_prev, self._p_prev, self._p_prev, np.full((3, robot.n), np.nan))
        # A compiled filter (momentum-form K-VARK) runs the whole step compiled (core.estimation.compiled_step; imported
        # here, so that the numpy path never loads numba).
        self._compiled = None
        if getattr(observer, "compiled", False):
            from kvark_ros.core.estimation.compiled_step import CompiledStep
            self._compiled = CompiledStep(robot, observer, self.tare, None if self._stiction is None
                                          else self._stiction.band, self._interval_scale, config, self.collision.z)
            self._p_prev, self._u_prev = self._compiled.previous
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
                                        urdf_sha256(config.urdf) if urdf is None else None)
        robot = RobotModel.from_config(config, model_augmentation(config, trained), urdf)
        return cls(config, robot, make_observer(name, trained, config.filter, oracle), trained)

    @property
    def compiled(self) -> bool:
        """Whether ``step`` runs as the compiled kernel (with a K-VARK momentum filter)."""
        return self._compiled is not None

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
        if self._compiled is not None:
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
        self._p_prev[:] = 0.0
        self._u_prev[:] = 0.0

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
        self._p_prev[:], self._u_prev[:] = other._p_prev, other._u_prev
        self._last_sample[:] = other._last_sample
        self.status = other.status
        self.contact.continue_from(other.contact)
        self.collision.continue_from(other.collision)
        self.tare.continue_from(other.tare)

    def _reject(self, status: str) -> None:
        self.status = status
        self.counts[status] += 1

    def step(self, stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> Estimate | None:
        """Process one sample (arrays in ``config.joint_names`` order). ``None`` while warming up or on rejection."""
        n = self.robot.n
        if q.shape != (n,) or qd.shape != (n,) or tau_m.shape != (n,):
            self._reject(Status.BAD_SHAPE)
            return None
        compiled = self._compiled
        if compiled is not None:
            finite = compiled.finite(stamp, q, qd, tau_m)
        else:
            # One reduction instead of three isfinite passes: NaN or Inf anywhere makes the sum non-finite, and
            # so does |x| > ~1e154 (overflow); that is a rejection, not a warning on stderr.
            with np.errstate(over="ignore", invalid="ignore"):
                finite = np.isfinite(stamp + q @ q + qd @ qd + tau_m @ tau_m)
        if not finite:
            self._reject(Status.NON_FINITE)
            return None
        previous = self._stamp
        gap_reset = False
        if previous is not None:
            if stamp <= previous:
                self._reject(Status.STAMP_NOT_INCREASING)
                return None
            if repeated_sample(stamp - previous, q, qd, tau_m, self._last_sample):
                # A stale state under a new stamp: stepping it would hold p for one period and then see the whole
                # catch-up as one momentum jump, which the onset detector takes for a contact (docs/method.md
                # §4.8). The next fresh sample's step spans both periods instead.
                self._reject(Status.REPEATED)
                return None
            if stamp - previous > self.config.input.max_gap:
                self.reset()
                self._reject(Status.GAP_RESET)
                previous, gap_reset = None, True
        if previous is None:
            self._last_sample[0], self._last_sample[1], self._last_sample[2] = q, qd, tau_m
            if compiled is not None:
                compiled.prime(q, qd, tau_m)
            else:
                self._p_prev, self._u_prev = self.robot.momentum_terms(q, qd, tau_m)
            self._stamp = stamp
            if not gap_reset:
                self._reject(Status.WARMUP)
            return None
        self._stamp = stamp
        if compiled is not None:
            return self._step_compiled(stamp, stamp - previous, q, qd, tau_m)
        p, u = self.robot.momentum_terms(q, qd, tau_m)
        p_prev, u_prev = self._p_prev, self._u_prev
        self._p_prev, self._u_prev = p, u
        g = self.robot.gravity(q) if "g" in self._needs else None
        tau_ext, tau_cov = self.observer.step(stamp - previous, qd, p, p_prev, u_prev, q, g)
        tau_ext = self.tare.apply(stamp, qd, tau_ext)         # τ̂ − offset (a non-finite τ̂ resets below)
        sticking = self._sticking_variance(qd)
        widened = reported = tau_cov                           # P of the tests, P the estimate reports
        scaled = False
        if tau_cov is not None:
            if sticking is not None:
                widened = tau_cov.copy()                       # the observer's own P stays as it is
                widened.flat[:: n + 1] += sticking             # Cov τ̂ + diag σ²_s(q̇) (docs/method.md §4.11)
            reported = widened
            if self._interval_scale is not None and self.config.filter.interval_calibration == "trained":
                # diag(c) P diag(c), with filter.interval_floor kf at least P_b under a load flagged by the last
                # sample's contact test, c_b² P_b in free motion, new (docs/method.md §4.13)
                reported = self._interval_scale.apply(tau_cov, self.config.filter.interval_floor == "kf",
                                                      self.contact.flag)
                if sticking is not None:
                    reported.flat[:: n + 1] += sticking
                scaled = True
        wrench, wrench_cov, weak, rotation, jacobian = self._solve_wrench(q, tau_ext, reported)
        total = tau_ext.sum() + (0.0 if tau_cov is None else reported.sum() + wrench_cov.sum())
        if not np.isfinite(total):
            return self._diverged()
        self.status = Status.OK
        self.counts[Status.OK] += 1
        covariance = self._test_covariance(q, qd, g, widened, sticking)
        # contact.test_covariance reported: the contact test's S is the reported Cov τ̂ (docs/method.md §7.2)
        tested = reported if scaled and self.config.contact.test_covariance == "reported" else covariance
        contact = self.contact.flag if tested is None else self.contact.update(stamp, tau_ext, tested)
        if sticking is not None and covariance is not None:
            # The collision flag is a safety stop with its own absolute threshold: it keeps the unwidened σ, so a
            # hit on a sticking joint is not delayed until it exceeds the static band (docs/method.md §4.11).
            covariance = covariance.copy()
            covariance.flat[:: n + 1] -= sticking
        collision = self.collision.update(tau_ext, covariance)
        if weak.shape[1]:
            self.unobservable_samples += 1
        return Estimate(stamp, tau_ext, reported, wrench, wrench_cov, contact, collision, self.config.wrench.frame,
                        rotation, jacobian, weak)

    def _step_compiled(self, stamp: float, dt: float, q: np.ndarray, qd: np.ndarray,
                       tau_m: np.ndarray) -> Estimate | None:
        """The rest of ``step`` as one compiled kernel (core.estimation.step_kernel), with the reference's outcomes."""
        self._compiled.load(self.contact.flag)      # the floor under a load flagged by the last sample (§4.13)
        singular, diverged, statistic, excess, tau_ext, tau_cov, wrench, wrench_cov, rotation, jacobian, weak = (
            self._compiled.step(stamp, dt, q, qd, tau_m, self.tare))
        if singular:              # wrench.damping 0 at a singular pose: the reference's answer (it refuses it)
            wrench, wrench_cov, weak, _, _ = self._solve_wrench(q, tau_ext, tau_cov)
            diverged = not np.isfinite(tau_ext.sum() + tau_cov.sum() + wrench_cov.sum())
        if diverged:
            return self._diverged()
        self.status = Status.OK
        self.counts[Status.OK] += 1
        contact = self.contact.decide(stamp, None if math.isnan(statistic) else statistic)
        collision = self.collision.decide(excess)
        if weak.shape[1]:
            self.unobservable_samples += 1
        return Estimate(stamp, tau_ext, tau_cov, wrench, wrench_cov, contact, collision, self.config.wrench.frame,
                        rotation, jacobian, weak)

    def _diverged(self) -> None:
        """A non-finite estimate: restart the filter, reject the sample."""
        self.reset()
        self._reject(Status.DIVERGED_RESET)

    def _solve_wrench(self, q: np.ndarray, tau_ext: np.ndarray, tau_cov: np.ndarray | None) -> tuple:
        """F, Σ_F and the weak directions of τ̂ in the axes of ``wrench.frame``, R and J (docs/method.md §1.4-1.4.1).

        One Jacobian per sample, in base axes: that pass also places the ee frame, whose rotation R gives the ee
        axes, F_ee = diag(Rᵀ, Rᵀ) F_base (the damped pseudo-inverse is rotation-covariant). That J also tells the
        weak directions (σ_i < δ); Σ_F carries the damping bias along them (§1.4.1).
        """
        settings = self.config.wrench
        solution = self.robot.solve_wrench(q, tau_ext, tau_cov, settings.damping, "base",
                                           (settings.prior_force, settings.prior_moment))
        wrench, wrench_cov, weak = solution.wrench, solution.cov, solution.weak
        rotation = self.robot.terms.ee_rotation.copy()
        if settings.frame != "base":
            wrench, wrench_cov = rotate_wrench(rotation.T, wrench, wrench_cov)
            if weak.shape[1]:
                weak = rotate_wrench(rotation.T, weak)[0]
        return wrench, wrench_cov, weak, rotation, solution.jacobian

    def _sticking_variance(self, qd: np.ndarray) -> np.ndarray | None:
        """σ²_s(q̇) (n,) N²·m² of the trained static friction band, or None when off (core.estimation.stiction)."""
        velocity = self.config.filter.stiction_velocity
        if self._stiction is None or velocity == 0.0:
            return None
        return self._stiction.variance(qd, velocity)

    def _test_covariance(self, q: np.ndarray, qd: np.ndarray, g: np.ndarray | None,
                         tau_cov: np.ndarray | None, sticking: np.ndarray | None) -> np.ndarray | None:
        """S of the contact and collision tests (class docstring), ``tau_cov`` already widened by the static friction
        band ``sticking`` (σ²_s (n,) or None); None without a covariance and a residual model (the contact flag then
        stays, the collision test takes σ = 0)."""
        if self.observer.uses_residual_model:
            mean, variance = self.observer.prediction
        elif self._contact_residual is not None:
            mean, variance = (self._contact_residual.predict(qd, q, g) if self._contact_residual.needs
                              else self._contact_residual.predict(qd))
        else:
            return tau_cov
        if tau_cov is None and sticking is not None:      # no P to carry the band: it joins the residual's variance
            variance = variance + sticking
        return contact_covariance(tau_cov, mean, variance, self.observer.uses_residual_model)
