"""What a ``kvark diagnose`` selection says, as ``diagnosis.json`` states it (``gap.diagnose``'s step 3): each chosen
effect with its parameters, 95 % half-widths, share of its prior and held-out share; the drive gains (measured with a
known load, or unidentified, ``gap.known_load``) and how far they may move a payload's mass; what the data want beyond
a prior, the explanation that explains most first; the at-bound warnings, look-alikes, the flange mass's regrouping and
the raw-signal gap (``gap.plausibility``); and the priors in force.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from kvark_ros.core.effect_catalog import BODY_EFFECTS
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import SAVGOL_WINDOW
from kvark_ros.gap.admissible import beyond_priors, prior_fields
from kvark_ros.gap.diagnosis_report import Diagnosis
from kvark_ros.gap.effects import Priors, Term, physical_parameters, variants
from kvark_ros.gap.fitting import Fitter
from kvark_ros.gap.known_load import KnownLoad, base_gains, gain_cells, gain_record, gain_width, load_centre
from kvark_ros.gap.plausibility import (RAW_QDD_WINDOW, beyond_prior_warning, flange_change, flange_mass_regrouping,
                                        look_alikes, plausibility_warnings, raw_gap)
from kvark_ros.gap.priors import UNITS
from kvark_ros.gap.selection import Fit, affected, contributions, per_joint, rmse


@dataclass(frozen=True)
class DiagnosisInputs:
    """What a diagnosis was asked: the robot (nominal, or a calibrated model), its free-motion recordings, the
    held-out share, the effect library, the priors in force and a known-load calibration's load (or None)."""

    robot: RobotModel
    segments: Sequence[EstimatorInputs]
    holdout: float
    effects: Sequence[str]
    priors: Priors
    load: KnownLoad | None = None
    started: float = field(default_factory=time.perf_counter)


def _gain_half_widths(inputs: DiagnosisInputs, effects: Sequence[dict],
                      centre: dict[str, Any] | None) -> tuple[np.ndarray, dict[str, Any]]:
    """The drive gains' 95 % half-widths (n,) a payload's mass is read through, and the ``drive_gains`` record: this
    diagnosis's known-load calibration (with the load's ``centre`` of mass, ``known_load.load_centre``), else the
    calibration it runs against (``known_load.base_gains``), else unidentified (the prior's bound on every joint)."""
    robot, priors = inputs.robot, inputs.priors
    record = base_gains(robot) if inputs.load is None else None
    if record is None:
        record = gain_record(effects, robot.n, priors.gain_bound, inputs.load, priors.torque_measurement, centre)
    half = np.minimum(np.asarray(record["ci95"], dtype=float), priors.gain_bound)
    return half, record


def state(inputs: DiagnosisInputs, fitter: Fitter, terms: list[Term], fit: Fit, log: Callable[[str], None],
          sample_interval: float) -> Diagnosis:
    """The ``Diagnosis`` of the chosen ``terms`` and their joint ``fit`` (module docstring), logged."""
    robot, priors, names = inputs.robot, inputs.priors, inputs.robot.joint_names
    theta, inverse, r_tr, r_he = fit
    beyond = beyond_priors(fitter, terms, affected)
    for record in beyond:
        log(f"[diagnose] beyond its prior: {beyond_prior_warning(record, priors, names)}")
    history = contributions(fitter, terms, r_he)
    cov = fitter.covariance(terms, inverse, r_tr)
    blocks = []
    pos = 0
    for term in [*terms, *fitter.nuisance]:
        blocks.append((theta[pos:pos + term.size], None if cov is None else cov[pos:pos + term.size,
                                                                                   pos:pos + term.size]))
        pos += term.size
    result_effects = []
    for term, info, (th, cv) in zip(terms, history, blocks):
        params, ci = physical_parameters(term, th, cv)
        joints = list(term.joints) if term.name not in BODY_EFFECTS else info["affected"]
        result_effects.append({"name": term.name, "joints": [int(j) for j in joints], "parameters": params,
                               "ci95": ci, **prior_fields(term, th, priors), "gap_reduction": info["gap_reduction"],
                               "held_out_rmse_before": info["held_out_rmse_before"],
                               "held_out_rmse_after": info["held_out_rmse_after"]})
    centre = None if inputs.load is None else load_centre(inputs.load, *blocks[len(terms)])
    half, gains = _gain_half_widths(inputs, result_effects, centre)
    for index, (term, effect) in enumerate(zip(terms, result_effects)):
        if term.name == "payload":       # its mass is read through the gains: their half-widths join the fit's
            th = blocks[index][0]
            effect["parameters"].update(flange_change(fitter.flange, fitter.flange_map, term.full_theta(th)))
            width = gain_width(fitter, terms, inverse, theta, index, half)
            effect["parameters"]["mass_gain_ci95"] = width
            if "mass" in effect["ci95"]:
                effect["ci95"]["mass"] = float(np.hypot(effect["ci95"]["mass"], width))
    thetas = [th for th, _ in blocks[:len(terms)]]
    gap_before, gap_after = rmse(fitter.held.gap), rmse(r_he)
    warnings = [*(beyond_prior_warning(record, priors, names) for record in beyond),
                *plausibility_warnings(terms, thetas, priors, names)]
    result = {
        "robot_joint_names": list(names),
        "gap_before": {"joint_rmse": gap_before.tolist(), "joint_rmse_mean": float(gap_before.mean())},
        "gap_after": {"joint_rmse": gap_after.tolist(), "joint_rmse_mean": float(gap_after.mean())},
        "gap_filtering": f"τ_m and q̇ through a {SAVGOL_WINDOW * 1e3:.0f} ms Savitzky-Golay filter (as kvark train)",
        "gap_raw": raw_gap(robot, inputs.segments, inputs.holdout, terms, thetas),
        "effects": result_effects,
        "drive_gains": gains,
        "priors": priors_in_force(priors),
        "beyond_priors": beyond,
        "warnings": warnings,
        "look_alikes": look_alikes({t.name: fitter.design(t)[0] for t in terms},
                                   {name: fitter.design(Term(name, tuple(range(robot.n)), variants(name, priors)[0]))[0]
                                    for name in inputs.effects}, fitter.w),
        "flange_mass": flange_mass_regrouping(fitter.train, robot),
        "against": None if robot.augmentation is None else robot.augmentation.source,
        "known_load_calibration": False,    # True: the gains of a known load, these effects from free motion alone
        "library": list(inputs.effects),
        "holdout": inputs.holdout, "samples": {"train": len(fitter.train), "held_out": len(fitter.held)},
        "seconds": round(time.perf_counter() - inputs.started, 1),
    }
    log(f"[diagnose] held-out gap per joint after (N·m): {per_joint(gap_after, names)} "
        f"(mean {gap_before.mean():.4f} → {gap_after.mean():.4f}); on raw τ_m with q̈ from a "
        f"{RAW_QDD_WINDOW * 1e3:.0f} ms filter {result['gap_raw']['before_mean']:.4f} → "
        f"{result['gap_raw']['after_mean']:.4f}")
    if inputs.load is not None:
        log(f"[diagnose] drive gains against the known load of {inputs.load.mass:g} kg: "
            + ", ".join(gain_cells(gains, names)))
    for warning in warnings:
        log(f"[diagnose] warning: {warning}")
    return Diagnosis(result, terms, thetas, fitter.held, r_he, sample_interval)


def priors_in_force(priors: Priors) -> dict:
    """Every effect's prior for ``diagnosis.json`` and the report: bound per joint (link_inertia per link: mass;
    payload: its mass), unit and source."""
    effects = {}
    for name, limit in priors.limits.items():
        values = np.asarray(limit, dtype=float)
        if name == "link_inertia":
            values = values.reshape(-1, 10)[:, 0]
        effects[name] = {"bound": [float(v) if np.isfinite(v) else None for v in values.reshape(-1)],
                         "unit": UNITS[name], "source": priors.sources.get(name, "")}
    return {"torque_measurement": priors.torque_measurement, "max_gain_error": priors.gain_bound,
            "max_joint_offset_deg": float(np.degrees(priors.max_joint_offset)), "flange_mass": priors.flange_mass,
            "effects": effects}
