"""``kvark diagnose``: where the nominal model and the measured data disagree, in physical terms.

1. the gap ``τ_m − τ_EL`` per joint on the recorded motion (q̈ and τ_m through the same
   Savitzky-Golay filter as ``kvark train``);
2. greedy forward selection over the named effects of ``kvark_ros.gap.effects``: samples are split
   in time (the last ``holdout`` share of every recording is held out); each round every
   (effect, joint set) candidate is fitted on the training part by bounded least squares within the
   priors (every effect within its prior scaled to the robot, ``gap.priors``; payload and link changes
   also with Gaussian priors toward the URDF and kept physically consistent), the one that
   lowers the held-out gap most is
   accepted when the BIC improves and the held-out gap of the affected joints drops by at least
   ``MIN_REDUCTION``; the search stops when no candidate is accepted. A backward pass then
   refits without each accepted effect in turn and drops the one whose removal costs least while
   removing it does not worsen the BIC or does not worsen the held-out gap of any joint by
   ``MIN_REDUCTION`` and ``MIN_ABS_REDUCTION`` (an effect accepted early can be made redundant
   by later ones, and a small effect can soak up what a later one explains); repeated until every
   remaining effect is needed. Because effects can look alike along a motion (a payload and drive
   gain errors both scale with gravity), greedy selection is run ``STARTS`` times, each from
   another acceptable first effect; a later selection replaces the kept one when it has a lower
   BIC with no more effects (BIC alone, with correlated samples, lets small spurious effects in:
   a run that trades one look-alike for the right effect ends with fewer of them). Every start begins
   from the URDF's priors; a candidate's tightened priors (physical consistency) are kept only when it
   is accepted. Each remaining effect's reported reduction is the held-out gap of all effects but that
   one against all of them;
3. refits the final set under the chosen start's priors until every link it changes is physically
   consistent, drops the joints (bodies) that the joint fit put at a bound of their prior (another effect
   seen through them, as at acceptance); against a calibrated model prefers a payload to link changes that
   explain no more (``payload_first``); names what the data want beyond a prior (``admissible.beyond_priors``)
   and the flag that allows it; and writes ``diagnosis.json``, ``augmentation.yaml`` (the accepted effects,
   loadable by ``effects.augmentation_gap``; against an augmented model, its effects first), ``report.md`` and
   plots (``gap.diagnosis_report``), with the warnings, look-alikes and raw-signal gap of ``gap.plausibility``.

Against a calibrated model the library is what changes between runs of one robot (``CHANGES_BETWEEN_RUNS``: a load,
friction, torque offsets); links, armature, gains, ripple and encoders are its construction, calibrated with it.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from kvark_ros.core.effect_catalog import BODY_EFFECTS, CHANGES_BETWEEN_RUNS, EFFECT_NAMES, PER_JOINT
from kvark_ros.core.estimation.augmentation import load_augmentation
from kvark_ros.core.config import ConfigError, EstimatorConfig, load_config
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.linalg import single_threaded_blas
from kvark_ros.core.estimation.model_store import TrainedModel, save_model
from kvark_ros.core.files import check_output, staged_directory
from kvark_ros.core.hints import did_you_mean
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import SAVGOL_WINDOW, smoothed_signals, train_model
from kvark_ros.core.estimation.robot_model import flange_link_parameters
from kvark_ros.gap.effects import (
    Priors,
    Signals,
    Term,
    flange_parameter_map,
    LINK_PRIOR,
    link_prior_scale,
    physical_parameters,
    signals,
    theta_split,
    variants,
)
from kvark_ros.gap.admissible import (bad_bodies, beyond_priors, consistent, inadmissible, prior_fields,
                                      saturated_joints, without_saturated)
from kvark_ros.gap.diagnosis_report import Diagnosis, write_outputs
from kvark_ros.gap.fitting import Fitter
from kvark_ros.gap.priors import FLAGS, MEASUREMENT_WIDTHS, UNITS, robot_priors
from kvark_ros.gap.plausibility import (
    RAW_QDD_WINDOW,
    beyond_prior_warning,
    flange_change,
    flange_mass_regrouping,
    look_alikes,
    plausibility_warnings,
    prior_summary,
    raw_gap,
)
from kvark_ros.io.alignment import add_sample_options, load_recordings
from kvark_ros.io.runs import numerical_failures

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

HOLDOUT = 0.3            # share of every recording (its end) held out
MIN_REDUCTION = 0.05     # an effect must cut the held-out gap of its joints by ≥ 5 %
MIN_ABS_REDUCTION = 0.005  # N·m, and by at least this much (filter noise floor)
DECIMATE_DT = 0.008      # s, sample spacing after smoothing (the filter passes far less than 60 Hz)
SCREEN_TOP = 4           # candidates refitted jointly per round
STARTS = 3               # greedy runs, each from another acceptable first effect (see module docstring)


def prepare(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float) -> tuple[Signals, Signals]:
    """(train, held-out) samples of every recording, filtered, trimmed and decimated."""
    train_idx, held_idx, parts = [], [], []
    offset = 0
    for seg in segments:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m)
        dt = float(np.median(np.diff(seg.stamp)))
        trim = int(round(SAVGOL_WINDOW / dt))
        step = max(1, int(round(DECIMATE_DT / dt)))
        keep = np.arange(trim, len(seg.stamp) - trim, step)
        if len(keep) < 20:
            continue
        parts.append((seg.q[keep], seg.qd[keep], qdd[keep], tau_m[keep]))
        split = int(round(len(keep) * (1.0 - holdout)))
        train_idx.append(offset + np.arange(split))
        held_idx.append(offset + np.arange(split, len(keep)))
        offset += len(keep)
    if not parts:
        raise ValueError("recordings too short to diagnose (need a few seconds of motion)")
    q, qd, qdd, tau = (np.concatenate([p[i] for p in parts]) for i in range(4))
    s = signals(robot, q, qd, qdd, tau)
    return s.take(np.concatenate(train_idx)), s.take(np.concatenate(held_idx))


def _rmse(r: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.square(r), axis=0))


def _screen(name: str, variant: dict, fitter: Fitter, terms: Sequence[Term], r_he: np.ndarray,
            n: int) -> Term | None:
    """Candidate joint set of one effect variant: the payload acts on every joint, a coupled effect
    is screened by ``_screen_coupled``, a per-joint effect keeps the joints whose held-out gap
    drops enough when it is added on that joint alone and everything is refitted."""
    if name in BODY_EFFECTS:
        return Term(name, tuple(range(n)), variant)
    if name not in PER_JOINT:
        return _screen_coupled(name, variant, fitter, terms, n)
    chosen = []
    held_rms = _rmse(r_he)
    for j in range(n):
        after = _rmse(fitter.fit([*terms, Term(name, (j,), variant)])[3])
        gain = held_rms[j] - after[j]
        if gain >= MIN_REDUCTION * held_rms[j] and gain >= MIN_ABS_REDUCTION:
            chosen.append(j)
    return Term(name, tuple(chosen), variant) if chosen else None


def _screen_coupled(name: str, variant: dict, fitter: Fitter, terms: Sequence[Term], n: int) -> Term | None:
    """Candidate joint set of a coupled effect (joint_offset): backward elimination from every joint
    whose regressor is not identically zero.

    A joint's parameter of a coupled effect acts on the gaps of other joints, and those joints
    interact (the UR5's parallel shoulder, elbow and wrist axes see sums of offsets), so an offset
    fitted on one joint alone can take the wrong sign to suit the small, heavily weighted gaps of
    the wrist joints. Starting from all of them, the joint whose removal raises the weighted
    held-out gap least is dropped while no joint's held-out gap worsens by ``MIN_REDUCTION`` and
    ``MIN_ABS_REDUCTION`` without it.
    """
    probe = fitter.design(Term(name, tuple(range(n)), variant))[0] * fitter.w[None, :, None]
    size = np.sqrt(np.mean(np.square(probe), axis=(0, 1)))
    chosen = [j for j in range(n) if size[j] > 1e-9 * max(float(size.max()), 1e-300)]
    if not chosen:
        return None
    after = _rmse(fitter.fit([*terms, Term(name, tuple(chosen), variant)])[3])
    while chosen:
        trials = []
        for j in chosen:
            rest = [i for i in chosen if i != j]
            without = _rmse(fitter.fit([*terms, Term(name, tuple(rest), variant)])[3]) if rest else None
            if without is None:
                without = _rmse(fitter.fit(list(terms))[3])
            if len(_affected(without, after)) == 0:
                trials.append((float(np.mean(np.square(without * fitter.w))), j, without))
        if not trials:
            break
        _, j, after = min(trials, key=lambda item: item[0])
        chosen.remove(j)
    return Term(name, tuple(chosen), variant) if chosen else None


def _named(joints: Sequence[int] | np.ndarray, names: Sequence[str]) -> str:
    """Joint indices as names, for log lines."""
    if len(joints) == len(names):
        return "every joint"
    return ", ".join(names[j] for j in joints) or "no joint"


def _per_joint(values: np.ndarray, names: Sequence[str]) -> str:
    """A value per joint (n,) with the joint's name, for log lines."""
    return ", ".join(f"{name} {value:.4f}" for name, value in zip(names, values))


def _affected(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Joints whose held-out gap drops by ≥ MIN_REDUCTION (relative) and MIN_ABS_REDUCTION."""
    drop = before - after
    return np.flatnonzero((drop >= MIN_REDUCTION * before) & (drop >= MIN_ABS_REDUCTION))


def _prune(fitter: Fitter, terms: list[Term], theta: np.ndarray, inverse: np.ndarray | None, r_tr: np.ndarray,
           r_he: np.ndarray, bic: float, log: Callable[[str], None], names: Sequence[str]) -> tuple:
    """Backward pass over the accepted terms (module docstring, step 2): (terms, θ, G⁻¹ (``Fitter.fit``),
    train and held-out residuals, BIC)."""
    terms = list(terms)
    if len(terms) > 1:
        log(f"[diagnose] backward pass over {len(terms)} effects ...")
    while len(terms) > 1:
        after = _rmse(r_he)
        k = sum(t.size for t in terms)
        drops = []
        for i, term in enumerate(terms):
            rest = terms[:i] + terms[i + 1:]
            fit = fitter.fit(rest)
            without = _rmse(fit[3])
            rest_bic = fitter.bic(fit[2], k - term.size)
            if rest_bic <= bic or len(_affected(without, after)) == 0:
                drops.append((float(np.mean(np.square(fit[3] * fitter.w))), i, fit, rest_bic, without))
        if not drops:
            break
        _, i, fit, rest_bic, without = min(drops, key=lambda item: item[0])
        log(f"[diagnose] dropped {terms[i].name} on {_named(terms[i].joints, names)} (backward pass): ΔBIC "
            f"{rest_bic - bic:+.1f}, held-out gap {np.round(after, 4).tolist()} → {np.round(without, 4).tolist()}")
        del terms[i]
        theta, inverse, r_tr, r_he = fit
        bic = rest_bic
    return terms, theta, inverse, r_tr, r_he, bic


def _contributions(fitter: Fitter, terms: list[Term], r_he: np.ndarray) -> list[dict]:
    """Each term's share: the held-out gap of all terms but that one against all of them."""
    after = _rmse(r_he)
    history = []
    for i, term in enumerate(terms):
        before = _rmse(fitter.fit(terms[:i] + terms[i + 1:])[3])
        joints = _affected(before, after)
        red = (1.0 - np.sqrt(np.mean(np.square(after[joints]))) / np.sqrt(np.mean(np.square(before[joints])))
               if len(joints) else 0.0)
        history.append({"affected": joints.tolist(), "gap_reduction": float(red),
                        "held_out_rmse_before": before[joints].tolist(),
                        "held_out_rmse_after": after[joints].tolist()})
    return history


def _scored_candidates(fitter: Fitter, terms: Sequence[Term], r_he: np.ndarray, effects: Sequence[str],
                       n: int) -> list[tuple]:
    """Every screened candidate added to ``terms`` and fitted: (weighted held-out error, term, fit),
    best first."""
    used = {t.name for t in terms}
    scored = []
    for name in effects:
        if name in used:
            continue
        for variant in variants(name, fitter.priors):
            term = _screen(name, variant, fitter, terms, r_he, n)
            if term is not None:
                fit = fitter.fit([*terms, term])
                scored.append((float(np.mean(np.square(fit[3] * fitter.w))), term, fit))
    scored.sort(key=lambda item: item[0])
    return scored


def _greedy(fitter: Fitter, effects: Sequence[str], names: Sequence[str], first_choice: int,
            first_round: list[tuple], log: Callable[[str], None]) -> tuple | None:
    """Forward selection and the backward pass (module docstring, step 2), starting in the first
    round from the acceptable candidate of the ``first_choice``-th distinct effect name (0 = the
    best candidate); None when the first round has fewer acceptable effects. Returns (terms, θ,
    G⁻¹, train and held-out residuals, BIC)."""
    terms: list[Term] = []
    theta, inverse, r_tr, r_he = fitter.fit(terms)
    bic = fitter.bic(r_tr, 0)
    while True:
        log(f"[diagnose] round {len(terms) + 1}: {len(effects) - len(terms)} of {len(effects)} effects to try on "
            f"top of {[t.name for t in terms]}, held-out gap {_rmse(r_he).mean():.3f} N·m ...")
        scored = first_round if not terms else _scored_candidates(fitter, terms, r_he, effects, len(names))
        accepted = False
        skip = first_choice if not terms else 0      # first round: effect names still to pass over
        passed: set[str] = set()
        before = _rmse(r_he)
        for score, term, (th, gi, rt, rh) in (scored if skip else scored[:SCREEN_TOP]):
            if term.name in passed:
                continue
            # A candidate's tightened priors (consistent) are kept only if it is accepted: a rejected one must not
            # constrain the bodies of the effects already in, nor the next candidates.
            priors_before = dict(fitter.prior_scale)
            term, (th, gi, rt, rh) = without_saturated(fitter, terms, term, th, gi, rt, rh)
            th, gi, rt, rh = consistent(fitter, [*terms, term], th, gi, rt, rh)
            k = sum(t.size for t in terms) + term.size
            new_bic = fitter.bic(rt, k)
            after = _rmse(rh)
            joints = _affected(before, after)
            problem = inadmissible(fitter, terms, term, th, names)
            if new_bic >= bic or len(joints) == 0 or problem is not None:
                log(f"[diagnose]   rejected {term.name} on {_named(term.joints, names)}: ΔBIC {new_bic - bic:+.1f}, "
                    f"{'' if problem is None else f'not physically admissible ({problem}), '}"
                    f"held-out gap {np.round(before, 4).tolist()} → {np.round(after, 4).tolist()}")
                fitter.prior_scale = priors_before
                continue
            if skip:
                skip -= 1
                passed.add(term.name)
                fitter.prior_scale = priors_before
                continue
            red = 1.0 - np.sqrt(np.mean(np.square(after[joints]))) / np.sqrt(np.mean(np.square(before[joints])))
            terms.append(term)
            old_bic = bic
            theta, inverse, r_tr, r_he, bic = th, gi, rt, rh, new_bic
            log(f"[diagnose] accepted {term.name} {dict(term.variant)} on {_named(term.joints, names)}: "
                f"held-out gap of {_named(joints, names)} −{red:.0%}, ΔBIC {new_bic - old_bic:+.0f}")
            accepted = True
            break
        if not accepted:
            if not terms and first_choice:
                return None
            break
    return _prune(fitter, terms, theta, inverse, r_tr, r_he, bic, log, names)


def diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float = HOLDOUT,
             effects: Sequence[str] | None = None, log: Callable[[str], None] = print, *,
             priors: Priors) -> Diagnosis:
    """Greedy selection of named effects explaining the gap (see module docstring), within ``priors`` (required:
    their width follows the robot's ``torque_measurement``; completed with the flange link's mass of ``robot`` and
    every effect's bounds derived from its URDF, ``gap.priors.robot_priors``; ``priors.payload_com`` fixes the
    payload's centre of mass). ``effects`` None: every effect; against a calibrated model (``robot.augmentation``)
    only ``CHANGES_BETWEEN_RUNS``."""
    effects = effects or (EFFECT_NAMES if robot.augmentation is None else CHANGES_BETWEEN_RUNS)
    flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    priors = robot_priors(robot, replace(priors, flange_mass=float(flange[0])))
    with single_threaded_blas():  # hundreds of small least-squares fits
        return _diagnose(robot, segments, holdout, effects, log, priors)


def body_fitter(robot: RobotModel, train: Signals, held: Signals, priors: Priors) -> Fitter:
    """The Fitter of a diagnosis: rows weighted by 1/max(training gap RMSE, 0.01 N·m), the URDF's bodies and the
    Gaussian priors of payload and link_inertia (docs/method.md §8.3)."""
    fitter = Fitter(train, held, 1.0 / np.maximum(_rmse(train.gap), 0.01), priors)
    fitter.flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    fitter.flange_map = flange_parameter_map(robot)[1]
    link_scale = link_prior_scale(robot)
    flange_moment = float(np.max(np.abs(fitter.flange[[4, 6, 9]])))
    # payload: free (a tool of any mass, CoM and inertia); only if the flange link comes out inconsistent do its
    # second moments get a prior, first 30 % of the flange link's largest moment (as link_inertia's), then halved.
    fitter.prior_scale = {"link_inertia": link_scale, "payload": np.full(10, np.inf)}
    fitter.first_prior = {"link_inertia": link_scale, "payload": np.concatenate(
        [np.full(4, np.inf), np.full(6, LINK_PRIOR["inertia"] * flange_moment)])}
    fitter.links = [robot.model.inertias[i].toDynamicParameters() for i in range(1, robot.n)]
    return fitter


def _diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float,
              effects: Sequence[str], log: Callable[[str], None], priors: Priors) -> Diagnosis:
    if not 0.05 <= holdout <= 0.9:
        raise ValueError(f"holdout must be in [0.05, 0.9], got {holdout}")
    unknown = sorted(set(effects) - set(EFFECT_NAMES))
    if unknown:
        raise ValueError(f"unknown effects {unknown}; known: {list(EFFECT_NAMES)}")
    started = time.perf_counter()
    train, held = prepare(robot, segments, holdout)
    n = robot.n
    log(f"[diagnose] {len(train)} training and {len(held)} held-out samples "
        f"(every {DECIMATE_DT * 1e3:.0f} ms, last {holdout:.0%} of each recording held out)")
    gap_before = _rmse(held.gap)
    fitter = body_fitter(robot, train, held, priors)
    log(f"[diagnose] held-out gap per joint before (N·m): {_per_joint(gap_before, robot.joint_names)}")
    log(f"[diagnose] fitting each of {len(effects)} effects alone (shared by the {STARTS} starts) ...")
    best, best_priors = None, None
    first_round = _scored_candidates(fitter, [], held.gap, effects, n)    # shared by every start
    initial_priors = dict(fitter.prior_scale)
    for start in range(STARTS):
        fitter.prior_scale = dict(initial_priors)     # every start from the URDF's priors, not the last start's
        found = _greedy(fitter, effects, robot.joint_names, start, first_round, lambda line, k=start + 1: log(
            line.replace("[diagnose]", f"[diagnose] start {k}/{STARTS}:")))
        if found is None:
            break
        score = float(np.sqrt(np.mean(np.square(found[4] * fitter.w))))
        log(f"[diagnose] start {start + 1}/{STARTS}: {[t.name for t in found[0]]}, BIC {found[-1]:.0f}, "
            f"weighted held-out gap {score:.4f}")
        if best is None or (found[-1] < best[-1] and len(found[0]) <= len(best[0])):
            best, best_priors = found, dict(fitter.prior_scale)
    terms, theta, inverse, r_tr, r_he, _ = best
    fitter.prior_scale = best_priors                  # the priors that selection ended with
    theta, inverse, r_tr, r_he = consistent(fitter, terms, *fitter.fit(terms))    # the pruned set refitted jointly
    while (bad := bad_bodies(fitter, terms, theta)):
        log(f"[diagnose] dropped {terms[bad[0][0]].name}: still physically inconsistent ({bad[0][2]})")
        terms = [t for i, t in enumerate(terms) if i != bad[0][0]]
        theta, inverse, r_tr, r_he = consistent(fitter, terms, *fitter.fit(terms))
    while (saturated := saturated_joints(fitter, terms, theta)):
        index, at_bound = saturated
        term = terms[index]
        keep = tuple(j for j in term.joints if j not in at_bound)
        log(f"[diagnose] dropped {term.name} on {_named(at_bound, robot.joint_names)}: at the bound of its prior "
            f"once fitted with the other effects (another effect seen through it)")
        terms = [*terms[:index], *([Term(term.name, keep, term.variant)] if keep else []), *terms[index + 1:]]
        theta, inverse, r_tr, r_he = consistent(fitter, terms, *fitter.fit(terms))
    if robot.augmentation is not None and "payload" in effects:
        terms, (theta, inverse, r_tr, r_he) = payload_first(fitter, terms, (theta, inverse, r_tr, r_he),
                                                            robot.joint_names, log)
    beyond = beyond_priors(fitter, terms, _affected)
    for record in beyond:
        log(f"[diagnose] beyond its prior: {beyond_prior_warning(record, priors, robot.joint_names)}")
    history = _contributions(fitter, terms, r_he)
    gap_after = _rmse(r_he)
    result_effects, thetas = [], []
    pos, cov = 0, fitter.covariance(terms, inverse, r_tr)
    for term, info in zip(terms, history):
        th = theta[pos:pos + term.size]
        cv = None if cov is None else cov[pos:pos + term.size, pos:pos + term.size]
        pos += term.size
        params, ci = physical_parameters(term, th, cv, priors.gain_bound)
        joints = list(term.joints) if term.name not in BODY_EFFECTS else info["affected"]
        if term.name == "payload":
            params.update(flange_change(fitter.flange, fitter.flange_map, term.full_theta(th)))
        result_effects.append({"name": term.name, "joints": [int(j) for j in joints], "parameters": params,
                               "ci95": ci, **prior_fields(term, th, priors), "gap_reduction": info["gap_reduction"],
                               "held_out_rmse_before": info["held_out_rmse_before"],
                               "held_out_rmse_after": info["held_out_rmse_after"]})
        thetas.append(th)
    result = {
        "robot_joint_names": list(robot.joint_names),
        "gap_before": {"joint_rmse": gap_before.tolist(), "joint_rmse_mean": float(gap_before.mean())},
        "gap_after": {"joint_rmse": gap_after.tolist(), "joint_rmse_mean": float(gap_after.mean())},
        "gap_filtering": f"τ_m and q̇ through a {SAVGOL_WINDOW * 1e3:.0f} ms Savitzky-Golay filter (as kvark train)",
        "gap_raw": raw_gap(robot, segments, holdout, terms, theta_split(terms, theta)),
        "effects": result_effects,
        "priors": _priors_in_force(priors),
        "beyond_priors": beyond,
        "warnings": [*plausibility_warnings(terms, theta_split(terms, theta), priors, robot.joint_names),
                     *(beyond_prior_warning(record, priors, robot.joint_names) for record in beyond)],
        "look_alikes": look_alikes({t.name: fitter.design(t)[0] for t in terms},
                                   {name: fitter.design(Term(name, tuple(range(n)), variants(name, priors)[0]))[0]
                                    for name in effects}, fitter.w),
        "flange_mass": flange_mass_regrouping(train, robot),
        "against": None if robot.augmentation is None else robot.augmentation.source,
        "library": list(effects),
        "holdout": holdout, "samples": {"train": len(train), "held_out": len(held)},
        "seconds": round(time.perf_counter() - started, 1),
    }
    log(f"[diagnose] held-out gap per joint after (N·m): {_per_joint(gap_after, robot.joint_names)} "
        f"(mean {gap_before.mean():.4f} → {gap_after.mean():.4f}); on raw τ_m with q̈ from a "
        f"{RAW_QDD_WINDOW * 1e3:.0f} ms filter {result['gap_raw']['before_mean']:.4f} → "
        f"{result['gap_raw']['after_mean']:.4f}")
    for warning in result["warnings"]:
        log(f"[diagnose] warning: {warning}")
    return Diagnosis(result, terms, thetas, held, r_he, DECIMATE_DT)


def payload_first(fitter: Fitter, terms: list[Term], fit: tuple, names: Sequence[str],
                   log: Callable[[str], None]) -> tuple[list[Term], tuple]:
    """Against a calibrated model: link_inertia replaced by a payload when the payload explains the held-out gap as
    well (no joint worse by ``MIN_REDUCTION`` and ``MIN_ABS_REDUCTION``) and is admissible. A new load on a calibrated
    robot is one body at the flange (10 parameters, its mass the identifiable combination with the link before it,
    ``plausibility.flange_mass_regrouping``), not changes of every link."""
    if "link_inertia" not in [t.name for t in terms] or "payload" in [t.name for t in terms]:
        return terms, fit
    index = [t.name for t in terms].index("link_inertia")
    payload = Term("payload", tuple(range(fitter.n)), variants("payload", fitter.priors)[0])
    rest = [t for i, t in enumerate(terms) if i != index]
    saved = dict(fitter.prior_scale)
    alternative = consistent(fitter, [*rest, payload], *fitter.fit([*rest, payload]))
    worse = _affected(_rmse(alternative[3]), _rmse(fit[3]))      # joints link_inertia explains better
    if len(worse) or inadmissible(fitter, rest, payload, alternative[0], names) is not None:
        fitter.prior_scale = saved
        return terms, fit
    log(f"[diagnose] against a calibrated model: payload instead of link_inertia (the same held-out gap within "
        f"{MIN_REDUCTION:.0%}; one body at the flange is the simpler explanation of a new load)")
    return [*rest, payload], alternative


def _priors_in_force(priors: Priors) -> dict:
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


def train_on_diagnosis(config: EstimatorConfig, robot: RobotModel, segments: Sequence[EstimatorInputs], out: Path,
                       baselines: bool, seed: int = 0,
                       log: Callable[[str], None] = print) -> tuple[TrainedModel, dict]:
    """Diagnose ``segments`` on ``robot`` (the nominal model) within the priors of ``config``'s torque measurement,
    as ``kvark diagnose`` does; write the outputs to ``out/diagnosis``, train on the model augmented with what was
    named and save it to ``out/model_augmented``. Returns the trained model and a summary: the effects, the mean
    held-out gap before/after (N·m) and the effects against their priors (``plausibility.prior_summary``)."""
    diagnosis = diagnose(robot, segments, log=log, priors=Priors(torque_measurement=config.torque_measurement))
    for path in write_outputs(diagnosis, robot, out / "diagnosis", config.robot):
        log(f"[diagnose] wrote {path}")
    augmentation = load_augmentation(out / "diagnosis" / "augmentation.yaml", config.joint_names)
    trained = train_model(RobotModel.from_config(config, augmentation), config.robot, segments, baselines=baselines,
                          seed=seed, log=log, settings=config.filter)
    save_model(out / "model_augmented", trained)
    return trained, {"effects": list(augmentation.effect_names),
                     "gap_before": diagnosis.result["gap_before"]["joint_rmse_mean"],
                     "gap_after": diagnosis.result["gap_after"]["joint_rmse_mean"],
                     "priors": prior_summary(diagnosis.result)}


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "diagnose", help="name the physical effects the nominal model lacks, from contact-free bags",
        description="Compute the gap τ_m − τ_EL between the commanded torque and the nominal model on "
                    "contact-free bags, select named physical effects (friction, armature, a payload or tool "
                    "mismatch at the flange, link inertial parameters, drive gain, torque offset, ripple, joint "
                    "offset) greedily on held-out data within plausible priors, every link kept physically "
                    "consistent, and write diagnosis.json, augmentation.yaml, report.md (with warnings and "
                    "look-alikes) and plots. An existing non-empty --out is replaced only with --force.")
    parser.add_argument("--config", required=True, help="estimator config YAML (e.g. config/panda.yaml)")
    parser.add_argument("--bags", nargs="+", required=True, metavar="BAG", help="contact-free bags")
    add_sample_options(parser, HOLDOUT, "share of every bag (its end) held out for selection")
    parser.add_argument("--out", required=True, help="output directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole (once the new output is complete)")
    parser.add_argument("--against", metavar="MODEL_DIR|AUGMENTATION",
                        help="diagnose relative to a model already corrected by this augmentation.yaml (or a model "
                             "directory's): only what changed since is named (a new tool on a calibrated robot), "
                             "from the effects that change between runs unless --effects says otherwise; the "
                             "written augmentation.yaml holds both")
    parser.add_argument("--payload-com", type=_com, metavar="X,Y,Z",
                        help="the payload's known centre of mass in the flange frame, m: only its mass and inertia "
                             "are fitted")
    parser.add_argument("--effects", type=_effect_list, default=None, metavar="A,B",
                        help=f"restrict the library to these effects (default all: {','.join(EFFECT_NAMES)}; with "
                             f"--against what changes between runs of one robot: {','.join(CHANGES_BETWEEN_RUNS)})")
    parser.add_argument("--max-gain-error", type=float, default=None, metavar="X",
                        help="prior of drive_gain: |1 − g| ≤ X (default from robot_model.torque_measurement: "
                             + ", ".join(f"{w['gain']:g} {m}" for m, w in MEASUREMENT_WIDTHS.items()) + ")")
    parser.add_argument("--max-joint-offset", type=float, default=float(np.degrees(Priors.max_joint_offset)),
                        metavar="DEG",
                        help="prior of joint_offset: |δ| ≤ DEG degrees (default 1; absolute encoders)")
    parser.add_argument("--prior", type=_prior_scale, action="append", default=[], metavar="EFFECT=FACTOR",
                        help="scale EFFECT's prior (derived from the URDF and robot_model.torque_measurement, "
                             "docs/method.md §8.6) by FACTOR, e.g. armature=2; repeatable")
    parser.add_argument("--no-plots", action="store_true", help="do not write plots")
    parser.set_defaults(run=run)


def _com(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z in metres, got {text!r}")
    return values


def _prior_scale(text: str) -> tuple[str, float]:
    name, value = (part.strip() for part in text.partition("=")[::2])
    if name in FLAGS:
        raise argparse.ArgumentTypeError(f"{name}'s prior has its own flag: {FLAGS[name]}")
    if name not in EFFECT_NAMES:
        raise argparse.ArgumentTypeError(f"unknown effect {name!r}{did_you_mean(name, EFFECT_NAMES)}; known: "
                                         f"{','.join(EFFECT_NAMES)}")
    try:
        factor = float(value)
    except ValueError:
        factor = float("nan")
    if not (np.isfinite(factor) and factor > 0):
        raise argparse.ArgumentTypeError(f"expected EFFECT=FACTOR with a positive FACTOR, got {text!r}")
    return name, factor


def _effect_list(text: str) -> tuple[str, ...]:
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = sorted(set(names) - set(EFFECT_NAMES))
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown effects {unknown or [text]}; known: {','.join(EFFECT_NAMES)}")
    return names


def run(args: argparse.Namespace) -> int:
    check_output(args.out, args.force, (*args.bags, args.against))
    config = load_config(args.config)
    base = None
    if args.against:
        source = Path(args.against)
        base = load_augmentation(source / "augmentation.yaml" if source.is_dir() else source, config.joint_names)
        print(f"[diagnose] relative to the model augmented by {base.source}: {', '.join(base.effect_names)}",
              flush=True)
    robot = RobotModel.from_config(config, base)
    print(f"[diagnose] URDF {config.urdf}", flush=True)
    segments = load_recordings(args.bags, config, "diagnose", tuple(args.trim), args.rate)
    log = lambda line: print(line, flush=True)   # noqa: E731
    if (args.max_gain_error is not None and args.max_gain_error <= 0) or args.max_joint_offset <= 0:
        raise ConfigError("--max-gain-error and --max-joint-offset must be positive")
    priors = Priors(max_gain_error=args.max_gain_error, max_joint_offset=float(np.radians(args.max_joint_offset)),
                    payload_com=args.payload_com, torque_measurement=config.torque_measurement,
                    scale=tuple(dict(args.prior).items()))
    out = Path(args.out)
    with numerical_failures(args.bags, "the diagnosis", "check the bags' skipped-sample lines above, --trim what is "
                            "not motion, or try one bag at a time"), staged_directory(out, args.force) as staging:
        diag = diagnose(robot, segments, args.holdout, effects=args.effects, log=log, priors=priors)
        written = write_outputs(diag, robot, staging, config.robot, plots=not args.no_plots)
    for path in written:
        log(f"[diagnose] wrote {out / path.relative_to(staging)}")
    return 0
