"""What a diagnosis says beyond its fit: implausible parameters, the tool change, the gap on raw torque.

* ``plausibility_warnings``: every parameter at a bound of its prior (``gap.priors``) is named with the flag that
  widens it, because the data wanted more than physics allows and another effect is probably hiding behind it;
  ``beyond_prior_warning``: an effect dropped at its prior that the data want beyond it (``admissible.beyond_priors``);
  ``prior_summary``: how much of its prior each named effect uses, and whether one outside it went unwarned;
* ``flange_change``: the payload effect as what it is physically: an unmodelled tool or payload (the flange
  link heavier than in the URDF) or a tool mismatch (lighter: the URDF's tool is not what the robot carries);
* ``flange_mass_regrouping``: whether the data can tell the flange link's mass from the link before it (on a
  serial arm whose flange lies on the last joint's axis they cannot: a base-parameter regrouping);
* ``raw_gap``: the held-out gap before/after on the raw measured torque with q̈ from a short filter
  (``RAW_QDD_WINDOW``), comparable to published identification figures; the selection itself runs on
  the 150 ms-filtered signals of ``kvark train``.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
from scipy.signal import savgol_filter

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.admissible import BOUND_SHARE, prior_hits
from kvark_ros.gap.effects import Priors, Signals, Term, signals
from kvark_ros.gap.priors import FAR_BEYOND, UNITS, suggested_flag

REGROUPED = 1e-6         # relative residual below which the flange mass is a combination of the previous link's
RAW_QDD_WINDOW = 0.05    # s: q̈ from a 50 ms Savitzky-Golay derivative of q̇; τ_m not filtered at all
OUTSIDE_TOLERANCE = 1e-6  # a share of its prior above 1 + this is outside it (bounded fits reach 1 + round-off)


def _value(name: str, theta: np.ndarray) -> str:
    """A per-joint effect's parameters (θ of one joint) as the report states them."""
    if name == "drive_gain":
        return f"g = {1.0 - theta[0]:.3f}"
    if name == "joint_offset":
        return f"{np.degrees(theta[0]):.2f}°"
    if name == "position_ripple":
        return f"amplitude {np.hypot(theta[0], theta[1]):.3g} N·m"
    return f"{theta[0]:.3g} {UNITS[name]}"


def _bound(name: str, bound: float) -> str:
    """A prior's bound as the report states it."""
    if name == "drive_gain":
        return f"±{bound:.0%}"
    if name == "joint_offset":
        return f"±{np.degrees(bound):.1f}°"
    return f"{bound:.3g} {UNITS[name]}"


def _flag(name: str, wanted: float, bound: float) -> str:
    return suggested_flag(name, wanted, bound) if np.isfinite(bound) and bound > 0 else f"--prior {name}=FACTOR"


def plausibility_warnings(terms: Sequence[Term], thetas: Sequence[np.ndarray], priors: Priors,
                          joint_names: Sequence[str]) -> list[str]:
    """One sentence per parameter at a bound of its prior (``Priors``), with the flag that widens it."""
    warnings = []
    for term, theta in zip(terms, thetas):
        lo, hi = term.bounds(priors)
        hits = prior_hits(term, theta, priors)
        if term.name == "payload":
            if theta[0] <= lo[0] + BOUND_SHARE * (abs(lo[0]) + 1.0):
                warnings.append(f"the flange link's mass change {theta[0]:.3f} kg removes all of its "
                                f"{priors.flange_mass:.3f} kg: the URDF's tool and link mass cannot explain the data")
            if hits[0]:
                warnings.append(f"the payload's mass {theta[0]:.3f} kg is at the bound of its prior ({hi[0]:.2f} kg: "
                                f"{priors.sources.get('payload', 'prior')}); if the robot really carries that much, "
                                f"pass {_flag('payload', theta[0], hi[0])}")
        elif term.name == "link_inertia":
            for link in np.flatnonzero(hits.reshape(-1, 10).any(axis=1)):
                warnings.append(f"the link moved by {joint_names[link]} changes at the bound of its prior "
                                f"({priors.sources.get('link_inertia', 'prior')}): pass --prior link_inertia=FACTOR "
                                "if its URDF is that far off")
        else:
            width = len(term.per_joint_parameters)
            for i, j in enumerate(term.joints):
                mine = theta[i * width:(i + 1) * width]
                if hits[i * width:(i + 1) * width].any():
                    bound = float(hi[i * width])
                    wanted = float(np.max(np.abs(mine)))
                    warnings.append(f"{term.name} of {joint_names[j]} is {_value(term.name, mine)}, at the bound of "
                                    f"its prior ({_bound(term.name, bound)}): another effect is probably seen "
                                    f"through it; if it is real, pass {_flag(term.name, wanted, bound)}")
    return warnings


def beyond_prior_warning(record: dict, priors: Priors, joint_names: Sequence[str]) -> str:
    """The sentence of one ``admissible.beyond_priors`` record: which effect wants which value, how far beyond which
    prior (× its bound), what it would explain, its weaker look-alikes, and what to change: the flag that allows it
    (for a drive gain where τ_m is not a link-side sensor's, also the known-load calibration that measures it). A
    record marked ``known_load`` comes from the fit with a known load, where the gain is left unidentified."""
    name, bound, wanted = record["effect"], record["bound"], record["wanted"]
    where = "" if record["joint"] < 0 else f" on {joint_names[record['joint']]}"
    if name == "drive_gain":
        want = f"|1 − g| ≈ {wanted:.3f}"
    elif name == "joint_offset":
        want = f"|δ| ≈ {np.degrees(wanted):.2f}°"
    else:
        want = f"{wanted:.3g} {UNITS[name]}"
    helped = ", ".join(f"{joint_names[j]} {b:.3f} → {a:.3f}" for j, b, a in zip(
        record["joints_helped"], record["held_out_before"], record["held_out_after"]))
    weaker = "; ".join(f"{other['effect']} ({other['wanted']:.3g} {UNITS[other['effect']]}, {other['ratio']:.1f}× "
                       f"its prior {_bound(other['effect'], other['bound'])}, gap → "
                       f"{', '.join(f'{a:.3f}' for a in other['held_out_after'])})"
                       for other in record.get("look_alikes", []))
    far = (f", far beyond it: check the robot's {name.replace('_', ' ')} before widening it"
           if record["ratio"] > FAR_BEYOND else "")
    known = bool(record.get("known_load"))     # from the fit with a known load (gap.diagnose): left unidentified
    measure = (" or measure the gains with a known mass at the flange (--known-load MASS BAG)"
               if name == "drive_gain" and priors.torque_measurement != "link_torque_sensor" and not known else "")
    verdict = ("Not accepted: the gain stays unidentified (its prior). If the value is physical, "
               f"pass {_flag(name, wanted, bound)}; otherwise another effect is seen through it in the recordings "
               "with the load (e.g. friction at velocity reversals, which the smooth friction effects do not follow)"
               if known else "Not accepted, and no look-alike outside its own prior stands in for it: if the value "
               f"is physical, pass {_flag(name, wanted, bound)}{measure}; otherwise an effect the library lacks is "
               "seen through it")
    return (("with the known load, " if known else "") + f"{name}{where} needs {want}, {record['ratio']:.1f}× its "
            f"prior {_bound(name, bound)} ({priors.sources.get(name, 'prior')}){far}; it would cut the held-out gap "
            f"(N·m{', the recordings with the load among them' if known else ''}) of {helped}. "
            + (f"Look-alikes that explain less, beyond their priors too: {weaker}. " if weaker else "") + verdict)


def prior_summary(result: Mapping[str, Any]) -> dict[str, Any]:
    """A diagnosis's named effects against their priors (``diagnosis.json``'s ``effects``, ``warnings`` and
    ``beyond_priors``): how many, the largest share of its prior any uses (``admissible.prior_use``), those at a
    bound (each a warning), the explanations wanted beyond a prior (each a warning) and the effects outside their
    prior with no warning (``unwarned``: a diagnosis should leave none; a fit within its bounds leaves a
    share above 1 by round-off only, ``OUTSIDE_TOLERANCE``)."""
    effects = result["effects"]
    uses = [effect["prior_use"] for effect in effects if effect.get("prior_use") is not None]
    outside = [effect for effect in effects if (effect.get("prior_use") or 0.0) > 1.0 + OUTSIDE_TOLERANCE]
    return {"effects": len(effects), "largest_prior_use": max(uses, default=None),
            "at_bound": [effect["name"] for effect in effects if effect.get("at_prior_bound")],
            "beyond_priors": len(result.get("beyond_priors", [])), "warnings": len(result["warnings"]),
            "unwarned": [effect["name"] for effect in outside
                         if not (effect.get("at_prior_bound") and result["warnings"])]}


def flange_change(flange: np.ndarray, flange_map: np.ndarray, theta: np.ndarray) -> dict:
    """The payload effect θ (10,) in the flange frame as a change of the flange link (``flange``: its URDF
    parameters, joint frame; ``flange_map``: flange → joint frame): kind, mass change, total mass, and each
    consistency claim checked on what it names (``core.estimation.payload.inertia_problem``): the changed flange
    link (``flange_link_consistent``, the check the selection applies), the payload as a body of its own (positive
    mass: ``payload_consistent``, its inertia about its centre positive semi-definite; None for a tool mismatch, which
    is no body), and ``physically_consistent`` for both. A payload whose own inertia is not a body's is a correction of
    the flange link, not a tool: the report says so."""
    total = flange + flange_map @ theta
    link = inertia_problem(total) is None
    own = None if theta[0] <= 0.0 else inertia_problem(theta) is None
    kind = ("tool mismatch: the robot's flange link is lighter than the URDF's (its tool is not the URDF's)"
            if theta[0] < 0.0 else "unmodelled payload or tool at the flange" if own
            else "a change of the flange link (its own inertia is not a body's: not a tool or load by itself)")
    return {"kind": kind, "mass_change": float(theta[0]), "flange_link_mass_urdf": float(flange[0]),
            "flange_link_mass_total": float(total[0]), "flange_link_consistent": link, "payload_consistent": own,
            "physically_consistent": link and own is not False}


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
