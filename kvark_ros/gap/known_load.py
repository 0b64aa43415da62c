"""A known-load calibration: what free motion cannot tell apart, read from a recording with a known mass at the flange
(``kvark diagnose --known-load MASS BAG``; docs/method.md §8).

Where τ_m is a gain times the motor current, a drive-gain error g_j scales joint j's whole torque. In free motion that
looks like a change of the links' inertia (a look-alike, cosine 0.98 on the population's arms), so a free-motion
calibration leaves the gains where the selection happened to put them; and a payload's torque passes through the same
gains, which scale its mass one to one. A load of known mass m at the flange adds a torque m·Y_m(q, q̇, q̈) that no link
change can imitate once m is fixed: stacked with the free-motion recordings, it pins the gains (Mamedov et al. 2020
identify the UR10e's that way, a loaded and an unloaded run with the load's mass known: ``estimate_drive_gains.m``).

On the known-load samples the gap is taken less the known part of the load (m's column of the flange regressor, and
m c's when its centre of mass is given); the load's unknown first and second moments are nuisance parameters of the
fit (``Fitter.nuisance``: fitted with every candidate, never selected nor written), its second moments with a Gaussian
prior toward zero of σ = m·``INERTIA_RADIUS``² (a load within that distance of the flange). ``drive_gain`` and
``link_inertia`` on every joint are forced into every selection (``Fitter.forced``): the load separates the gains
from the links only when both are fitted. The gains are reported with their 95 % intervals: a payload's mass is read
through them afterwards (``gain_width``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.effects import Priors, Signals, Term
from kvark_ros.gap.fitting import Fitter

NAME = "known_load"
INERTIA_RADIUS = 0.2        # m: prior σ of the load's second moments about the flange origin, m·(0.2 m)²
FORCED = ("drive_gain", "link_inertia")   # what the load separates: the gains from the links
FIRST_MOMENTS = ("mx", "my", "mz")
SECOND_MOMENTS = ("ixx", "ixy", "iyy", "ixz", "iyz", "izz")


@dataclass(frozen=True)
class KnownLoad:
    """A mass fixed to the flange during some recordings: ``mass`` kg, its centre of mass ``com`` (flange frame, m)
    or None (fitted), the recordings' ``segments`` and where they come from (``source``, for the report)."""

    mass: float
    com: tuple[float, float, float] | None = None
    segments: Sequence[EstimatorInputs] = field(default_factory=tuple)
    source: str = ""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.mass) and self.mass > 0.0):
            raise ValueError(f"the known load's mass must be a positive number of kg, got {self.mass}")
        if self.com is not None and (len(self.com) != 3 or not np.all(np.isfinite(self.com))):
            raise ValueError(f"the known load's centre of mass must be three finite numbers (m), got {self.com}")

    @property
    def unknown(self) -> tuple[str, ...]:
        """The load's parameters the fit reads (its mass is known; with a given CoM its first moments too)."""
        return SECOND_MOMENTS if self.com is not None else (*FIRST_MOMENTS, *SECOND_MOMENTS)

    def known_parameters(self) -> np.ndarray:
        """The known part of the load's 10 parameters [m, m c, I_origin] (flange frame): m, and m c with a CoM."""
        known = np.zeros(10)
        known[0] = self.mass
        if self.com is not None:
            known[1:4] = self.mass * np.asarray(self.com, dtype=float)
        return known

    def prior_scale(self) -> np.ndarray:
        """Gaussian prior σ of the unknown moments: none (∞) on the first moments, m·``INERTIA_RADIUS``² on the
        second."""
        return np.array([np.inf if name in FIRST_MOMENTS else self.mass * INERTIA_RADIUS ** 2 for name in self.unknown])


@dataclass(frozen=True)
class LoadTerm(Term):
    """The known load's unknown moments as a nuisance term: its regressor is ``Signals.known_load``."""

    count: int = len(SECOND_MOMENTS)

    @property
    def per_joint_parameters(self) -> tuple[str, ...]:
        return (*FIRST_MOMENTS, *SECOND_MOMENTS)[-self.count:]

    @property
    def size(self) -> int:
        return self.count

    def bounds(self, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self.count, -np.inf), np.full(self.count, np.inf)

    def design(self, s: Signals) -> np.ndarray:
        if s.known_load is None:
            raise ValueError("these samples carry no known-load regressor")
        return s.known_load


def load_signals(s: Signals, loaded: np.ndarray, load: KnownLoad) -> Signals:
    """``s`` with the known load taken into account on the rows ``loaded`` (T,) bool: the gap less the load's known
    torque (``KnownLoad.known_parameters`` through the flange regressor), and the regressor of its unknown moments
    (zero on the other rows) as ``known_load``.

    Nothing else of the loaded recording is free: a torque offset of its own would take the mean of the load's
    gravity torque, which is what measures the gains (on the population's UR5 #4 of seed 27 an own offset per joint
    left the elbow's gain at its prior's bound, 1.078 drawn). So the loaded recording must share the unloaded ones'
    offsets and friction: record it right after an unloaded run of the same motion (``tools.sim_bags``)."""
    index = [1 + (*FIRST_MOMENTS, *SECOND_MOMENTS).index(name) for name in load.unknown]
    known = s.payload_regressor @ load.known_parameters()
    mask = loaded.astype(float)[:, None]
    return replace(s, gap=s.gap - mask * known, known_load=s.payload_regressor[:, :, index] * mask[:, :, None])


def calibrate_with(fitter: Fitter, load: KnownLoad) -> None:
    """Make ``fitter`` a known-load calibration's: the load's unknown moments as its nuisance term (with their prior)
    and ``FORCED`` on every joint forced into the selection."""
    term = LoadTerm(NAME, tuple(range(fitter.n)), count=len(load.unknown))
    fitter.nuisance = (term,)
    fitter.prior_scale[NAME] = load.prior_scale()
    fitter.forced = tuple(Term(name, tuple(range(fitter.n))) for name in FORCED)


def load_centre(load: KnownLoad, theta: np.ndarray, cov: np.ndarray | None) -> dict[str, Any]:
    """What the calibration read of the known load (its nuisance θ and covariance): its centre of mass c = (m c)/m
    (flange frame, m) with 95 % half-widths, or the given one."""
    if load.com is not None:
        return {"com": [float(v) for v in load.com], "com_given": True}
    sd = np.full(3, np.nan) if cov is None else np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None))
    return {"com": (theta[:3] / load.mass).tolist(), "com_ci95": (1.96 * sd / load.mass).tolist(), "com_given": False}


def gain_cells(record: Mapping[str, Any], joint_names: Sequence[str]) -> list[str]:
    """Each joint's drive gain of a ``gain_record`` as the log and the reports write it: ``name g ± h`` (95 %), or
    ``name not identified (±h prior)`` where the data did not narrow it below the prior."""
    return [f"{name} {g:.3f} ± {h:.3f}" if ok else f"{name} not identified (±{h:.2f} prior)"
            for name, g, h, ok in zip(joint_names, record["gain"], record["ci95"], record["identified"])]


def gain_record(effects: Sequence[Mapping[str, Any]], n: int, bound: float, load: KnownLoad | None,
                measurement: str, centre: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``drive_gains`` of diagnosis.json and augmentation.yaml: the gain per joint (1 where none is named), its 95 %
    half-width (the prior's ``bound`` where the data did not narrow it) and whether it was identified. Without a known
    load every gain is unidentified, named or not: free motion cannot tell it from the links' inertia.
    ``mass_share``: the largest share of a payload's mass the gains may move it by (``gain_width`` gives the payload's
    own figure)."""
    gain, half = np.ones(n), np.full(n, bound)
    identified = np.zeros(n, dtype=bool)
    for effect in effects:
        if effect["name"] == "drive_gain":
            for j, value, width in zip(effect["joints"], effect["parameters"]["gain"], effect["ci95"]["gain"]):
                gain[j] = value       # as named; its interval only where a known load measured it
                if load is not None and np.isfinite(width):
                    identified[j] = bool(width < bound)
                    half[j] = min(float(width), bound)
    record: dict[str, Any] = {
        "calibrated_with": None if load is None else {"mass_kg": load.mass, "source": load.source, **(centre or {})},
        "torque_measurement": measurement, "prior": bound, "gain": gain.tolist(), "ci95": half.tolist(),
        "identified": identified.tolist(), "mass_share": float(half.max())}
    return record


def base_gains(robot: RobotModel) -> dict[str, Any] | None:
    """The ``drive_gains`` record of the calibration ``robot`` is augmented with, or None (no augmentation, or one
    written before the record existed)."""
    if robot.augmentation is None:
        return None
    record = (yaml.safe_load(robot.augmentation.text) or {}).get("drive_gains")
    if record is None:
        return None
    if not isinstance(record, Mapping) or len(record.get("ci95") or ()) != robot.n:
        raise ValueError(f"{robot.augmentation.source}: drive_gains needs ci95 with one value per joint "
                         f"({robot.n}); write it with `kvark diagnose`")
    return dict(record)


def gain_width(fitter: Fitter, terms: Sequence[Term], inverse: np.ndarray | None, theta: np.ndarray, index: int,
               half: np.ndarray) -> float:
    """95 % half-width (kg) a payload's mass carries from the drives' gains: Σ_j |c_j| h_j, c_j = ∂m̂/∂δ_j the change
    of the fitted mass when joint j's measured torque is off by a factor 1 + δ_j (linearised: the mass row of
    G⁻¹ Aᵀ W² applied to the payload's own torque on joint j alone), h_j ``half`` (n,) the gains' 95 % half-widths;
    the worst case of aligned errors (every drive of one robot warms alike). Σ_j c_j is the mass itself, so with every
    h_j = h the width is at least h·|m|: a gain error scales the payload one to one (``terms[index]``: the payload)."""
    if inverse is None:
        return float("nan")
    pos = sum(term.size for term in terms[:index])
    own = fitter.design(terms[index])[0] @ theta[pos:pos + terms[index].size]           # (T, n) N·m
    moments = np.einsum("tjp,j,tj->pj", fitter.stacked(terms), np.square(fitter.w), own, optimize=True)   # (p, n)
    sensitivity = (inverse @ moments)[pos]                                                  # ∂m̂/∂δ_j, kg
    return float(np.sum(np.abs(sensitivity) * np.asarray(half, dtype=float)))
