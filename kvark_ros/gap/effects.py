"""Library of named physical effects, each a linear-in-parameters regressor of the model gap.

The gap is ``τ_m − τ_EL`` (paper eq. 27) on a contact-free motion: what the commanded torque
spends beyond the nominal rigid-body model. Every effect adds ``Φ(q, q̇, q̈, τ_m) θ`` to it, with
the sign chosen so that θ is the physical parameter (sign conventions of ``kvark_ros.sim.plant``):

* ``coulomb_friction``  ``F_c tanh(q̇/ε)``, F_c ≥ 0 N·m, ε from a small grid (a sharp sign for dry
  friction, a gentle one for the sigmoid friction of real gearboxes);
* ``viscous_friction``  ``F_v q̇``, F_v ≥ 0 N·m·s/rad;
* ``stribeck_friction`` ``(F_s − F_c) exp(−(q̇/v_s)²) tanh(q̇/ε)``, ≥ 0, v_s from a small grid;
* ``armature``          ``I_a q̈``, I_a ≥ 0 kg·m² (rotor inertia seen at the joint);
* ``payload``           ``Y_flange(q, q̇, q̈) π``: the change of the 10 inertial parameters of the
  flange's link, in the flange frame (pinocchio's joint-torque regressor of that link): an unmodelled
  tool or payload (mass > 0) or a tool mismatch (mass < 0: the URDF's tool is heavier than what the
  robot carries), admissible while the link's total inertia stays physically consistent;
* ``link_inertia``      ``Y_links(q, q̇, q̈) Δπ``: changes of the 10 inertial parameters of every link but the
  flange's (joint frames; CAD errors of mass, centre of mass, inertia), regularised toward the URDF by a
  Gaussian prior (``LINK_PRIOR``): directions the data do not identify stay at the URDF; admissible while
  every link stays physically consistent;
* ``drive_gain``        the drive applies ``g τ_m``: gap ``(1 − g) τ_m``; reported as g;
* ``torque_offset``     the drive applies ``τ_m + o``: gap ``−o``;
* ``position_ripple``   the drive applies ``a sin(k q) + b cos(k q)``: gap ``−(a sin + b cos)``;
* ``joint_offset``      the encoder reads ``q + δ``: gap ``−∂τ_EL/∂q_j δ_j`` (first order: gravity,
  inertia and Coriolis sensitivity, pinocchio's RNEA derivatives).

The effects, their order, parameters, bounds and grids are the lines of ``core.effect_catalog``; the torque
effects' columns are ``core.estimation.augmentation.joint_columns``, the structural ones' regressors are here.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Any, Mapping, Sequence

import numpy as np
import pinocchio as pin

# The library is ``core.effect_catalog`` (one line an effect); EFFECT_NAMES and PER_JOINT are re-exported from it.
from kvark_ros.core.effect_catalog import EFFECT_NAMES, EFFECTS_BY_NAME, MEASUREMENT_WIDTHS, PER_JOINT  # noqa: F401
from kvark_ros.core.estimation.augmentation import joint_columns
from kvark_ros.core.estimation.robot_model import RobotModel

MIN_MASS = 1e-3                               # kg, smallest total mass of the flange's link
# Prior standard deviations of link_inertia (CAD-like errors): mass 20 % of the link's, first moment
# m·3 cm + 20 %, second moments 30 % of the link's largest moment about its origin.
LINK_PRIOR = {"mass": 0.2, "com_m": 0.03, "first_moment": 0.2, "inertia": 0.3}


@dataclass(frozen=True)
class Priors:
    """Plausible ranges the fit is bounded to (``gap.priors``, docs/method.md §8.6); a parameter at one of them is
    dropped, and a warning when the data want it beyond.

    max_gain_error: |1 − g| of drive_gain; None: the share of ``torque_measurement`` (``gap.priors``).
    max_joint_offset: |δ| of joint_offset, rad. 1° by default: absolute encoders are calibrated at the
        factory; a larger offset is a gravity-like effect (link mass, CoM) in disguise.
    flange_mass: the URDF's mass of the flange's link with what is fixed to it (kg); a tool mismatch can
        remove at most that.
    payload_com: a payload's known centre of mass (flange frame, m): only its mass and inertia are fitted.
    torque_measurement: how τ_m is measured (``robot_model.torque_measurement``): the priors' width.
    scale: (effect, factor) pairs of ``--prior EFFECT=FACTOR``, each effect's derived bounds times the factor.
    limits: |θ| bound per effect (per joint; link_inertia 10 per link; payload its mass), from
        ``gap.priors.robot_priors``; an effect without one is bounded only by ``max_gain_error`` /
        ``max_joint_offset`` (drive gain, joint offset) or not at all.
    sources: where each bound comes from, for the report.
    physics: |θ| beyond which a value is not that effect at all (a drive gain near zero, a ripple or an offset larger
        than the joint's whole effort), from ``gap.priors.robot_priors``; what the data want beyond a prior is
        offered only inside it (``admissible.beyond_priors``). An effect without one: no such bound.
    """

    max_gain_error: float | None = None
    max_joint_offset: float = float(np.radians(1.0))
    flange_mass: float = 0.0
    payload_com: tuple[float, float, float] | None = None
    torque_measurement: str = "motor_current"
    scale: tuple[tuple[str, float], ...] = ()
    limits: Mapping[str, np.ndarray] = field(default_factory=dict)
    sources: Mapping[str, str] = field(default_factory=dict)
    physics: Mapping[str, np.ndarray] = field(default_factory=dict)

    @property
    def gain_bound(self) -> float:
        """|1 − g| of drive_gain: ``max_gain_error``, else the torque measurement's share."""
        if self.max_gain_error is not None:
            return self.max_gain_error
        return MEASUREMENT_WIDTHS[self.torque_measurement]["gain"]

    def limit(self, name: str) -> np.ndarray | float | None:
        """The |θ| bound of effect ``name`` (an array from ``limits``, a scalar for every joint), or None."""
        if name in self.limits:
            return self.limits[name]
        return {"drive_gain": self.gain_bound, "joint_offset": self.max_joint_offset}.get(name)


@dataclass(frozen=True, eq=False)
class Signals:
    """Samples of one or more motions: q, q̇, q̈, smoothed τ_m, gap (T, n); payload regressor
    (T, n, 10) in the flange frame; position sensitivity ∂τ_EL/∂q (T, n, n); the other links' regressor; and, with a
    known-load recording among the motions, the regressor (T, n, p) of that load's unknown parameters, zero on the
    samples without it (``gap.known_load``), else None."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_m: np.ndarray
    gap: np.ndarray
    payload_regressor: np.ndarray
    position_jacobian: np.ndarray
    link_regressor: np.ndarray
    known_load: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.q)

    def take(self, index: np.ndarray) -> "Signals":
        return Signals(*(getattr(self, f)[index] for f in ("q", "qd", "qdd", "tau_m", "gap",
                                                            "payload_regressor", "position_jacobian",
                                                            "link_regressor")),
                       known_load=None if self.known_load is None else self.known_load[index])


def flange_parameter_map(robot: RobotModel) -> tuple[int, np.ndarray]:
    """(joint id of the flange's link, A (10, 10)) with ``π_joint = A π_flange``.

    The map is linear (a change of reference frame of a spatial inertia), so it is fixed exactly by
    ten linearly independent physical inertias.
    """
    frame = robot.model.frames[robot.flange_frame_id]
    rng = np.random.default_rng(0)
    flange, joint = [], []
    for _ in range(10):
        a = rng.standard_normal((3, 3))
        inertia = pin.Inertia(1.0 + rng.random(), rng.standard_normal(3) * 0.1, a @ a.T + 0.1 * np.eye(3))
        flange.append(inertia.toDynamicParameters())
        joint.append(frame.placement.act(inertia).toDynamicParameters())
    flange_m, joint_m = np.array(flange).T, np.array(joint).T
    return frame.parentJoint, joint_m @ np.linalg.inv(flange_m)


def signals(robot: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, tau_m: np.ndarray) -> Signals:
    """Gap and the regressors that need the model, for samples (T, n); relative to ``robot``'s augmentation if it
    has one."""
    model, data = robot.model, robot.data
    jid, a_map = flange_parameter_map(robot)
    t, n = q.shape
    gap = np.empty((t, n))
    payload = np.empty((t, n, 10))
    sensitivity = np.empty((t, n, n))
    links = np.empty((t, n, 10 * (jid - 1)))
    for k in range(t):
        # model_torque: τ_EL plus, on an augmented model (kvark diagnose --against), the torque effects it has
        gap[k] = tau_m[k] - robot.model_torque(q[k], qd[k], qdd[k], tau_m[k])
        q_model = robot.model_position(q[k])
        y = pin.computeJointTorqueRegressor(model, data, q_model, qd[k], qdd[k])
        payload[k] = y[:, 10 * (jid - 1):10 * jid] @ a_map
        links[k] = y[:, :10 * (jid - 1)]
        pin.computeRNEADerivatives(model, data, q_model, qd[k], qdd[k])
        sensitivity[k] = data.dtau_dq
    return Signals(q, qd, qdd, tau_m, gap, payload, sensitivity, links)


def link_prior_scale(robot: RobotModel) -> np.ndarray:
    """Prior standard deviations (10 per link before the flange's, ``LINK_PRIOR``) of link_inertia's Δπ."""
    jid = robot.model.frames[robot.flange_frame_id].parentJoint
    scales = []
    for i in range(1, jid):
        pi = robot.model.inertias[i].toDynamicParameters()
        m = max(float(pi[0]), 0.1)
        moment = max(float(np.max(np.abs(pi[[4, 6, 9]]))), m * LINK_PRIOR["com_m"] ** 2)
        scales.append(np.concatenate([[LINK_PRIOR["mass"] * m],
                                      m * LINK_PRIOR["com_m"] + LINK_PRIOR["first_moment"] * np.abs(pi[1:4]),
                                      np.full(6, LINK_PRIOR["inertia"] * moment)]))
    return np.concatenate(scales)


@dataclass(frozen=True)
class Term:
    """One effect on a set of joints: its regressor block and parameter layout.

    ``variant`` holds the fixed (non-linear) settings, e.g. ``{"stribeck_velocity": 0.1}``.
    """

    name: str
    joints: tuple[int, ...]
    variant: Mapping[str, float] = field(default_factory=dict)

    @property
    def per_joint_parameters(self) -> tuple[str, ...]:
        """Names of the parameters each joint carries (payload: of the whole body), from the catalog."""
        return EFFECTS_BY_NAME[self.name].parameters

    @property
    def size(self) -> int:
        k = len(self.per_joint_parameters)
        if self.name == "link_inertia":
            return k * (len(self.joints) - 1)          # every link but the flange's
        if self.name == "payload":
            return len(self.parameter_index())
        return k * len(self.joints)

    @property
    def fixed_com(self) -> np.ndarray | None:
        """A payload's known centre of mass (3,) m, flange frame (``kvark diagnose --payload-com``), or None."""
        if self.name != "payload" or "com_x" not in self.variant:
            return None
        return np.array([self.variant["com_x"], self.variant["com_y"], self.variant["com_z"]])

    def parameter_index(self) -> np.ndarray:
        """Which of the 10 payload parameters are fitted: all, or with a known CoM mass and inertia (the first
        moments follow as m c)."""
        return np.arange(10) if self.fixed_com is None else np.array([0, 4, 5, 6, 7, 8, 9])

    def full_theta(self, theta: np.ndarray) -> np.ndarray:
        """The payload's 10 parameters from the fitted ones (identity for every other effect)."""
        com = self.fixed_com
        if com is None:
            return theta
        return np.concatenate([[theta[0]], theta[0] * com, theta[1:]])

    def bounds(self, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of θ (size,) under ``priors``: the physical ones (θ ≥ 0, the flange link's mass
        > 0) and the priors' |θ| ≤ bound (drive_gain: θ = 1 − g)."""
        lo, hi = np.full(self.size, -np.inf), np.full(self.size, np.inf)
        entry = EFFECTS_BY_NAME[self.name]
        if entry.nonnegative:
            lo[:] = 0.0
        limit = priors.limit(self.name)
        if self.name == "payload":        # the link's total mass stays positive, a payload within the prior's mass
            lo[0] = MIN_MASS - priors.flange_mass
            if limit is not None:
                hi[0] = float(np.asarray(limit).reshape(-1)[0])
        elif self.name == "link_inertia":
            if limit is not None:
                hi = np.asarray(limit, dtype=float).copy()
                lo = -hi
        elif limit is not None:
            per_joint = np.asarray(limit, dtype=float)
            values = per_joint[list(self.joints)] if per_joint.ndim else np.full(len(self.joints), float(per_joint))
            hi = np.repeat(values, len(self.per_joint_parameters))
            lo = np.zeros_like(hi) if entry.nonnegative else -hi
        return lo, hi

    def design(self, s: Signals) -> np.ndarray:
        """Regressor block (T, n, size): gap rows × parameters."""
        t, n = s.q.shape
        if self.name == "payload":
            com = self.fixed_com
            if com is None:
                return s.payload_regressor
            y = s.payload_regressor          # first moments m c: their columns fold into the mass column
            return np.concatenate([y[:, :, :1] + y[:, :, 1:4] @ com[:, None], y[:, :, 4:]], axis=2)
        if self.name == "link_inertia":
            return s.link_regressor
        out = np.zeros((t, n, self.size))
        for i, j in enumerate(self.joints):
            if self.name == "joint_offset":
                out[:, :, i] = -s.position_jacobian[:, :, j]
                continue
            if self.name == "armature":
                cols = [s.qdd[:, j]]
            else:
                cols = joint_columns(self.name, self.variant, s.q[:, j], s.qd[:, j], s.tau_m[:, j])
            width = len(cols)
            for c, col in enumerate(cols):
                out[:, j, i * width + c] = col
        return out


def variants(name: str, priors: Priors | None = None) -> list[dict[str, float]]:
    """The fixed settings an effect is tried with (a payload's known CoM comes from ``priors``)."""
    if name == "payload" and priors is not None and priors.payload_com is not None:
        return [dict(zip(("com_x", "com_y", "com_z"), map(float, priors.payload_com)))]
    grid = EFFECTS_BY_NAME[name].grid        # every combination of the catalog's grid, its keys in order
    return [dict(zip(grid, map(float, values))) for values in product(*grid.values())]


def theta_split(terms: Sequence[Term], theta: np.ndarray) -> list[np.ndarray]:
    """θ of a joint fit cut into each term's parameters."""
    cuts = np.cumsum([0] + [term.size for term in terms])
    return [theta[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


def physical_parameters(term: Term, theta: np.ndarray, cov: np.ndarray | None) -> tuple[dict, dict]:
    """Parameters in physical units and their 95 % half-widths of the fit (delta method for derived ones; a payload's
    mass also carries the drives' gains, added by ``gap.diagnosis_result`` with ``known_load.gain_width``)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if cov is not None else np.full(len(theta), np.nan)
    half = 1.96 * sd
    if term.name == "payload":
        if term.fixed_com is not None:           # covariance of the 10 parameters through θ_full = T φ
            jac = np.zeros((10, term.size))
            jac[0, 0], jac[1:4, 0], jac[4:, 1:] = 1.0, term.fixed_com, np.eye(6)
            cov = None if cov is None else jac @ cov @ jac.T
        return payload_parameters(term.full_theta(theta), cov)
    if term.name == "link_inertia":     # per link, joint frame: Δm kg, Δ(m c) kg·m, ΔI kg·m² about the origin
        values, widths = theta.reshape(-1, 10), half.reshape(-1, 10)
        return ({"mass_change": values[:, 0].tolist(), "first_moment_change": values[:, 1:4].tolist(),
                 "inertia_change": values[:, 4:].tolist()},
                {"mass_change": widths[:, 0].tolist(), "first_moment_change": widths[:, 1:4].tolist()})
    k = len(term.per_joint_parameters)
    values = theta.reshape(len(term.joints), k)
    widths = half.reshape(len(term.joints), k)
    if term.name == "drive_gain":     # gap = (1 − g) τ_m: θ = 1 − g
        return {"gain": (1.0 - values[:, 0]).tolist()}, {"gain": widths[:, 0].tolist()}
    if term.name == "position_ripple":
        a, b = values[:, 0], values[:, 1]
        params = {"cycles_per_rev": term.variant["cycles_per_rev"], "sin_amplitude": a.tolist(),
                  "cos_amplitude": b.tolist(), "amplitude": np.hypot(a, b).tolist()}
        return params, {"sin_amplitude": widths[:, 0].tolist(), "cos_amplitude": widths[:, 1].tolist()}
    key = term.per_joint_parameters[0]
    params: dict[str, Any] = {key: values[:, 0].tolist()}
    params.update({name: value for name, value in term.variant.items()})
    return params, {key: widths[:, 0].tolist()}


def payload_parameters(theta: np.ndarray, cov: np.ndarray | None) -> tuple[dict, dict]:
    """Mass, CoM (flange frame) and inertia about the CoM ``[ixx, iyy, izz, ixy, ixz, iyz]`` of a payload change, and
    the fit's 95 % half-widths of mass and CoM. Its physical consistency is checked on the flange link it changes and
    on itself (``plausibility.flange_change``). The payload's torque is measured through the drives' gains, which the
    data cannot tell from its mass (g m fits as well): ``gap.diagnosis_result`` adds their share to the mass's
    half-width (``known_load.gain_width``); the CoM, a ratio, is not moved by them."""
    m, h = float(theta[0]), np.asarray(theta[1:4], dtype=float)
    com = h / m
    ixx, ixy, iyy, ixz, iyz, izz = theta[4:10]
    i_origin = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    i_com = i_origin - m * (float(com @ com) * np.eye(3) - np.outer(com, com))
    eig = np.linalg.eigvalsh(i_com)
    params = {"mass": m, "com": com.tolist(),
              "inertia": [float(v) for v in (i_com[0, 0], i_com[1, 1], i_com[2, 2], i_com[0, 1], i_com[0, 2],
                                             i_com[1, 2])],
              "inertia_eigenvalues": eig.tolist()}
    ci: dict[str, Any] = {}
    if cov is not None:
        ci["mass"] = 1.96 * float(np.sqrt(max(cov[0, 0], 0.0)))
        com_ci = []
        for i in range(3):
            grad = np.zeros(10)
            grad[0], grad[1 + i] = -h[i] / m ** 2, 1.0 / m
            com_ci.append(1.96 * float(np.sqrt(max(grad @ cov @ grad, 0.0))))
        ci["com"] = com_ci
    return params, ci


def term_from_entry(entry: Mapping[str, Any], joint_names: Sequence[str]) -> tuple[Term, np.ndarray]:
    """A Term and its raw parameter vector θ from one ``augmentation.yaml`` effect entry."""
    joints = tuple(int(j) for j in entry["joint_indices"])
    # a file's payload θ is always the 10 parameters, also when diagnose fitted it with a known CoM
    variant = {k: float(v) for k, v in (entry.get("variant") or {}).items() if not k.startswith("com_")}
    term = Term(entry["name"], joints, variant)
    return term, np.asarray(entry["theta"], dtype=float)


def augmentation_gap(augmentation: Mapping[str, Any], robot: RobotModel, q: np.ndarray, qd: np.ndarray,
                     qdd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
    """Predicted gap ``τ_m − τ_EL`` (T, n) of an augmentation (the dict of ``augmentation.yaml``):
    what an estimator subtracts from its residual to run on the improved model."""
    q, qd, qdd, tau_m = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (q, qd, qdd, tau_m))
    s = signals(robot, q, qd, qdd, tau_m)
    total = np.zeros_like(q)
    for entry in augmentation.get("effects", []):
        term, theta = term_from_entry(entry, robot.joint_names)
        total += term.design(s) @ theta
    return total
