"""What a diagnosis says beyond its fit: implausible parameters, the tool change, the gap on raw torque.

* ``plausibility_warnings``: every parameter at a bound of its prior (drive gain, joint offset, the flange
  link's mass) is named, because the data wanted more than physics allows and another effect is probably
  hiding behind it;
* ``flange_change``: the payload effect as what it is physically: an unmodelled tool or payload (the flange
  link heavier than in the URDF) or a tool mismatch (lighter: the URDF's tool is not what the robot carries);
* ``flange_mass_regrouping``: whether the data can tell the flange link's mass from the link before it (on a
  serial arm whose flange lies on the last joint's axis they cannot: a base-parameter regrouping);
* ``raw_gap``: the held-out gap before/after on the raw measured torque with q̈ from a short filter
  (``RAW_QDD_WINDOW``), comparable to published identification figures; the selection itself runs on
  the 150 ms-filtered signals of ``kvark train``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.signal import savgol_filter

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.effects import Priors, Signals, Term, signals

REGROUPED = 1e-6         # relative residual below which the flange mass is a combination of the previous link's
RAW_QDD_WINDOW = 0.05    # s: q̈ from a 50 ms Savitzky-Golay derivative of q̇; τ_m not filtered at all
BOUND_SHARE = 0.01       # a parameter within 1 % of its prior's range from a bound is "at the bound"


def theta_split(terms: Sequence[Term], theta: np.ndarray) -> list[np.ndarray]:
    """θ of a joint fit cut into each term's parameters."""
    cuts = np.cumsum([0] + [term.size for term in terms])
    return [theta[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


def plausibility_warnings(terms: Sequence[Term], thetas: Sequence[np.ndarray], priors: Priors,
                          joint_names: Sequence[str]) -> list[str]:
    """One sentence per parameter at a bound of its prior (``Priors``)."""
    warnings = []
    for term, theta in zip(terms, thetas):
        lo, hi = term.bounds(priors)
        finite = np.isfinite(lo) & np.isfinite(hi)
        span = np.where(finite, np.where(finite, hi, 0.0) - np.where(finite, lo, 0.0), np.abs(np.where(
            np.isfinite(lo), lo, 0.0)) + 1.0)      # one-sided bound: 1 % of |bound| + 1 in the parameter's unit
        at_low = np.isfinite(lo) & (theta <= np.where(np.isfinite(lo), lo, 0.0) + BOUND_SHARE * span)
        at_high = np.isfinite(hi) & (theta >= np.where(np.isfinite(hi), hi, 0.0) - BOUND_SHARE * span)
        if term.name == "drive_gain":
            for j, value, low, high in zip(term.joints, theta, at_low, at_high):
                if low or high:
                    warnings.append(f"drive_gain of {joint_names[j]} is {1.0 - value:.3f}, at the bound of its prior "
                                    f"(±{priors.max_gain_error:.0%}): another effect is seen through τ_m")
        elif term.name == "joint_offset":
            for j, value, low, high in zip(term.joints, theta, at_low, at_high):
                if low or high:
                    warnings.append(f"joint_offset of {joint_names[j]} is {np.degrees(value):.2f}°, at the bound of "
                                    f"its prior (±{np.degrees(priors.max_joint_offset):.1f}°): probably a link's "
                                    "mass or centre of mass, not the encoder")
        elif term.name == "payload" and at_low[0]:
            warnings.append(f"the flange link's mass change {theta[0]:.3f} kg removes all of its "
                            f"{priors.flange_mass:.3f} kg: the URDF's tool and link mass cannot explain the data")
    return warnings


def flange_change(flange: np.ndarray, flange_map: np.ndarray, theta: np.ndarray) -> dict:
    """The payload effect θ (10,) in the flange frame as a change of the flange link (``flange``: its URDF
    parameters, joint frame; ``flange_map``: flange → joint frame): kind, mass change, total mass and whether the
    changed link is physically consistent (``core.estimation.payload.inertia_problem``, the check the selection
    applies)."""
    total = flange + flange_map @ theta
    kind = ("tool mismatch: the robot's flange link is lighter than the URDF's (its tool is not the URDF's)"
            if theta[0] < 0.0 else "unmodelled payload or tool at the flange")
    return {"kind": kind, "mass_change": float(theta[0]), "flange_link_mass_urdf": float(flange[0]),
            "flange_link_mass_total": float(total[0]), "physically_consistent": inertia_problem(total) is None}


def flange_mass_regrouping(s: Signals, robot: RobotModel) -> dict | None:
    """Whether a mass change at the flange is identified apart from the link before the flange's link: the
    least-squares residual of the payload regressor's mass column (T·n,) on that link's 10 inertial-parameter
    columns, relative to the column's norm (``REGROUPED``: not identified). None without such a link.

    A point mass on the last joint's axis moves with the previous link whatever that joint does, so its torques
    are exactly those of a change of the previous link's mass, first moment and inertia (the base-parameter
    regrouping of identification): a tool's mass is then read relative to that link's URDF values."""
    if s.link_regressor.shape[2] < 10:
        return None
    mass = s.payload_regressor[:, :, 0].reshape(-1)
    previous = s.link_regressor[:, :, -10:].reshape(-1, 10)
    coefficients = np.linalg.lstsq(previous, mass, rcond=None)[0]
    residual = float(np.linalg.norm(mass - previous @ coefficients) / max(np.linalg.norm(mass), 1e-300))
    joint = robot.model.names[robot.model.frames[robot.flange_frame_id].parentJoint - 1]
    return {"link_before_flange": f"the link moved by {joint}", "relative_residual": residual,
            "identified": residual >= REGROUPED}


def raw_gap(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float, terms: Sequence[Term],
            thetas: Sequence[np.ndarray]) -> dict:
    """Held-out gap RMSE per joint (N·m) on raw τ_m, q̈ from a ``RAW_QDD_WINDOW`` filter, before and after the
    accepted effects; every sample of the last ``holdout`` of each recording except the filter's edges."""
    parts = []
    for seg in segments:
        dt = float(np.median(np.diff(seg.stamp)))
        window = max(5, int(round(RAW_QDD_WINDOW / dt)) | 1)
        if len(seg.stamp) <= 2 * window:
            continue
        qdd = np.gradient(savgol_filter(seg.qd, window, 3, axis=0), seg.stamp, axis=0)
        start = max(int(round(len(seg.stamp) * (1.0 - holdout))), window)
        keep = np.arange(start, len(seg.stamp) - window)
        parts.append((seg.q[keep], seg.qd[keep], qdd[keep], seg.tau_m[keep]))
    if not parts:
        return {"before": [], "after": [], "before_mean": float("nan"), "after_mean": float("nan")}
    s = signals(robot, *(np.concatenate([p[i] for p in parts]) for i in range(4)))
    after = s.gap.copy()
    for term, theta in zip(terms, thetas):
        after -= term.design(s) @ theta
    before_rmse, after_rmse = (np.sqrt(np.mean(np.square(g), axis=0)) for g in (s.gap, after))
    return {"filter": f"raw τ_m, q̈ from a {RAW_QDD_WINDOW * 1e3:.0f} ms Savitzky-Golay derivative of q̇",
            "before": before_rmse.tolist(), "after": after_rmse.tolist(),
            "before_mean": float(before_rmse.mean()), "after_mean": float(after_rmse.mean())}


COLLINEAR_COSINE = 0.95  # largest canonical correlation above which two effects look alike on the data


def look_alikes(accepted: dict[str, np.ndarray], others: dict[str, np.ndarray], weights: np.ndarray) -> list[dict]:
    """Pairs of effects the data hardly tell apart: for each accepted effect's regressor block (T, n, p) and every
    other effect of the library (all joints), the cosine of the smallest principal angle between their weighted
    column spaces (1: some combination of one is exactly one of the other); pairs at or above ``COLLINEAR_COSINE``.

    The selection kept the accepted one by BIC, the held-out gap and the priors; the pair says which physical
    reading the data alone could not exclude (a drive gain on a gravity-loaded joint looks like a payload)."""
    from scipy.linalg import subspace_angles

    def columns(block: np.ndarray) -> np.ndarray:
        a = (block * weights[None, :, None]).reshape(-1, block.shape[2])
        return a[:, np.linalg.norm(a, axis=0) > 1e-12]

    pairs = []
    for name, block in accepted.items():
        a = columns(block)
        for other, other_block in others.items():
            b = columns(other_block)
            if other == name or a.shape[1] == 0 or b.shape[1] == 0:
                continue
            cosine = float(np.cos(np.min(subspace_angles(a, b))))
            if cosine >= COLLINEAR_COSINE:
                pairs.append({"accepted": name, "look_alike": other, "cosine": round(cosine, 4)})
    return pairs
