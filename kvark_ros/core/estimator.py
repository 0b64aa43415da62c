"""The estimator: robot model + observer, one call per sample.

The same object runs behind the ROS node and the bag replay, so live and offline results
are identical for identical inputs.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from kvark_ros.core.augmentation import Augmentation, AugmentationError, load_augmentation
from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.contact import ContactDetector, contact_covariance
from kvark_ros.core.model_store import TrainedModel, load_model
from kvark_ros.core.observers import Observer, ResidualPredictor, make_observer
from kvark_ros.core.robot_model import RobotModel, urdf_sha256


@dataclass(frozen=True)
class Estimate:
    """One output sample; torque acting on the robot (docs/method.md §1.2).

    tau_ext: (n,) N·m; tau_cov: (n, n) N²·m²; wrench: (6,) [N, N·m] at the end-effector frame
    origin, axes of ``wrench_frame``; wrench_cov: (6, 6). The covariances are ``None`` for
    observers that report no uncertainty. contact: the debounced contact flag (docs/method.md §7).
    """

    stamp: float
    tau_ext: np.ndarray
    tau_cov: np.ndarray | None
    wrench: np.ndarray
    wrench_cov: np.ndarray | None
    contact: bool


class Status:
    """Outcome of the last ``Estimator.step``; also the keys of ``Estimator.counts``."""

    OK = "ok"
    WARMUP = "warm-up: first sample after start or reset"
    BAD_SHAPE = "rejected: q, qd or tau_m has the wrong length"
    NON_FINITE = "rejected: NaN, Inf or an overflowing value (|x| > 1e150) in q, qd or tau_m"
    STAMP_NOT_INCREASING = "rejected: stamp not after the previous sample (out of order or duplicate)"
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


class Estimator:
    """Steps an observer on (stamp, q, q̇, τ_m) samples and maps τ_ext to a wrench.

    Bad samples never reach the filter: they are rejected (``step`` returns ``None``), counted
    in ``counts`` and described by ``status``. The output is always finite.

    The contact test (``contact``, a ``ContactDetector``) runs on every estimate with
    S = P + diag σ²_r(q̇) from the observer's own residual model; an observer without one falls back
    to the trained KMP with its mean as uncertainty too (docs/method.md §7), which needs ``trained``.
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
        # Pose inputs of the residual model in use (observer's or contact test's): g(q) costs a pinocchio pass.
        self._needs = observer.needs | frozenset(getattr(self._contact_residual, "needs", ()))
        self.contact = ContactDetector(robot.n, config.contact.confidence, config.contact.debounce)
        self.counts: Counter[str] = Counter()
        self.status = Status.WARMUP
        self.reset()

    @classmethod
    def from_config(cls, config: EstimatorConfig, trained: TrainedModel | None = None,
                    observer: str | None = None, urdf: str | None = None,
                    oracle: ResidualPredictor | None = None) -> "Estimator":
        """Build robot model and observer from the config; ``trained`` defaults to ``config.model_dir``.

        ``urdf`` overrides ``config.urdf`` (the node passes the ``robot_description`` string);
        ``oracle`` is the true residual (the simulator's ``OracleResidual``), for the ``oracle``
        observer only, whose robot model is built on the oracle's ``urdf`` (the plant's true rigid body)
        when it has one.
        """
        name = observer or config.observer
        if name == "oracle" and urdf is None:
            urdf = getattr(oracle, "urdf", None)
        trained = trained or load_model(config.model_dir, config.joint_names,
                                        urdf_sha256(config.urdf) if urdf is None else None)
        robot = RobotModel.from_config(config, model_augmentation(config, trained), urdf)
        return cls(config, robot, make_observer(name, trained, config.filter, oracle), trained)

    def configure(self, config: EstimatorConfig) -> None:
        """Apply a config whose run-time keys changed (config_schema.KEYS ``runtime``), from the next sample.

        The estimator reads ``input.max_gap`` and ``wrench.*`` from ``config``; the observer takes
        ``config.filter`` (``Observer.configure``: a changed key that is not run-time raises
        ``ValueError`` and nothing changes).
        """
        self.observer.configure(config.filter)
        self.contact.configure(config.contact.confidence, config.contact.debounce)
        self.config = config

    def reset(self) -> None:
        """Restart from the next sample (filter state, previous sample and contact state forgotten)."""
        self.observer.reset()
        self.contact.reset()
        self._stamp: float | None = None
        self._p_prev = np.zeros(self.robot.n)
        self._u_prev = np.zeros(self.robot.n)

    def continue_from(self, other: "Estimator") -> None:
        """Continue from ``other``'s state, so that swapping it for this one changes no output (model reload).

        Copies the previous sample (stamp, p, u), ``status``, the observer's filter state and the
        contact detector's state; ``counts`` stay this estimator's own. Raises ``ValueError`` (and
        changes nothing) unless both have the same joints and the same observer class and name, or
        if the observer states do not fit (``Observer.load_state``).
        """
        if self.config.joint_names != other.config.joint_names:
            raise ValueError("cannot continue from an estimator with other joints")
        mine, theirs = self.observer, other.observer
        if type(mine) is not type(theirs) or mine.name != theirs.name:
            raise ValueError(f"cannot continue observer '{mine.name}' ({type(mine).__name__}) from "
                             f"'{theirs.name}' ({type(theirs).__name__})")
        mine.load_state(theirs.state())
        self._stamp = other._stamp
        self._p_prev, self._u_prev = other._p_prev.copy(), other._u_prev.copy()
        self.status = other.status
        self.contact.continue_from(other.contact)

    def _reject(self, status: str) -> None:
        self.status = status
        self.counts[status] += 1

    def step(self, stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> Estimate | None:
        """Process one sample (arrays in ``config.joint_names`` order). ``None`` while warming up or on rejection."""
        n = self.robot.n
        if q.shape != (n,) or qd.shape != (n,) or tau_m.shape != (n,):
            self._reject(Status.BAD_SHAPE)
            return None
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
            if stamp - previous > self.config.input.max_gap:
                self.reset()
                self._reject(Status.GAP_RESET)
                previous, gap_reset = None, True
        p, u = self.robot.momentum_terms(q, qd, tau_m)
        p_prev, u_prev = self._p_prev, self._u_prev
        self._stamp, self._p_prev, self._u_prev = stamp, p, u
        if previous is None:
            if not gap_reset:
                self._reject(Status.WARMUP)
            return None
        g = self.robot.gravity(q) if "g" in self._needs else None
        tau_ext, tau_cov = self.observer.step(stamp - previous, qd, p, p_prev, u_prev, q, g)
        wrench, wrench_cov = self.robot.wrench_from_torque(q, tau_ext, tau_cov, self.config.wrench.damping,
                                                           self.config.wrench.frame)
        total = tau_ext.sum() + (0.0 if tau_cov is None else tau_cov.sum() + wrench_cov.sum())
        if not np.isfinite(total):
            self.reset()
            self._reject(Status.DIVERGED_RESET)
            return None
        self.status = Status.OK
        self.counts[Status.OK] += 1
        flag = self._contact_flag(stamp, q, qd, g, tau_ext, tau_cov)
        return Estimate(stamp, tau_ext, tau_cov, wrench, wrench_cov, flag)

    def _contact_flag(self, stamp: float, q: np.ndarray, qd: np.ndarray, g: np.ndarray | None, tau_ext: np.ndarray,
                      tau_cov: np.ndarray | None) -> bool:
        """The debounced contact flag after this estimate (class docstring); unchanged without a covariance."""
        if self.observer.uses_residual_model:
            mean, variance = self.observer.prediction
        elif self._contact_residual is not None:
            mean, variance = (self._contact_residual.predict(qd, q, g) if self._contact_residual.needs
                              else self._contact_residual.predict(qd))
        elif tau_cov is None:
            return self.contact.flag
        else:
            return self.contact.update(stamp, tau_ext, tau_cov)
        covariance = contact_covariance(tau_cov, mean, variance, self.observer.uses_residual_model)
        return self.contact.update(stamp, tau_ext, covariance)
