"""Greedy selection of named effects on held-out data, the search of ``kvark diagnose`` (``gap.diagnose`` prepares
the data and states the result; module docstring there, step 2-3).

Every round fits each (effect, joint set) candidate on top of the accepted ones (``Fitter``), accepts the one that
lowers the held-out gap most when the BIC improves and the held-out gap of the joints it acts on drops by
``MIN_REDUCTION`` and ``MIN_ABS_REDUCTION``; a backward pass drops what later effects made redundant; ``STARTS``
greedy runs begin from another acceptable first effect; ``select`` keeps the best run and refits it until every body
is physically consistent and no effect sits at the bound of its prior. The fitter's ``forced`` terms (the drive
gains of a known-load calibration) are in every run from the start and never dropped by the backward pass.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from kvark_ros.core.effect_catalog import BODY_EFFECTS, PER_JOINT
from kvark_ros.gap.admissible import (bad_bodies, consistent, inadmissible, saturated_joints, without_saturated)
from kvark_ros.gap.effects import Term, variants
from kvark_ros.gap.fitting import Fitter

MIN_REDUCTION = 0.05     # an effect must cut the held-out gap of its joints by ≥ 5 %
MIN_ABS_REDUCTION = 0.005  # N·m, and by at least this much (filter noise floor)
SCREEN_TOP = 4           # candidates refitted jointly per round
STARTS = 3               # greedy runs, each from another acceptable first effect (see module docstring)
Fit = tuple              # (θ, G⁻¹, train residual, held-out residual) of ``Fitter.fit``


def rmse(r: np.ndarray) -> np.ndarray:
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
    held_rms = rmse(r_he)
    for j in range(n):
        after = rmse(fitter.held_out([*terms, Term(name, (j,), variant)]))
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
    after = rmse(fitter.held_out([*terms, Term(name, tuple(chosen), variant)]))
    while chosen:
        trials = []
        for j in chosen:
            rest = [i for i in chosen if i != j]
            without = rmse(fitter.held_out([*terms, Term(name, tuple(rest), variant)])) if rest else None
            if without is None:
                without = rmse(fitter.held_out(list(terms)))
            if len(affected(without, after)) == 0:
                trials.append((float(np.mean(np.square(without * fitter.w))), j, without))
        if not trials:
            break
        _, j, after = min(trials, key=lambda item: item[0])
        chosen.remove(j)
    return Term(name, tuple(chosen), variant) if chosen else None


def named(joints: Sequence[int] | np.ndarray, names: Sequence[str]) -> str:
    """Joint indices as names, for log lines."""
    if len(joints) == len(names):
        return "every joint"
    return ", ".join(names[j] for j in joints) or "no joint"


def per_joint(values: np.ndarray, names: Sequence[str]) -> str:
    """A value per joint (n,) with the joint's name, for log lines."""
    return ", ".join(f"{name} {value:.4f}" for name, value in zip(names, values))


def affected(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Joints whose held-out gap drops by ≥ MIN_REDUCTION (relative) and MIN_ABS_REDUCTION."""
    drop = before - after
    return np.flatnonzero((drop >= MIN_REDUCTION * before) & (drop >= MIN_ABS_REDUCTION))


def prune(fitter: Fitter, terms: list[Term], theta: np.ndarray, inverse: np.ndarray | None, r_tr: np.ndarray,
           r_he: np.ndarray, bic: float, log: Callable[[str], None], names: Sequence[str]) -> tuple:
    """Backward pass over the accepted terms but the fitter's forced ones (module docstring, step 2): (terms, θ,
    G⁻¹ (``Fitter.fit``), train and held-out residuals, BIC)."""
    terms = list(terms)
    if len(terms) > 1:
        log(f"[diagnose] backward pass over {len(terms)} effects ...")
    while len(terms) > 1:
        after = rmse(r_he)
        k = sum(t.size for t in terms)
        drops = []
        for i, term in enumerate(terms):
            if term in fitter.forced:
                continue
            rest = terms[:i] + terms[i + 1:]
            fit = fitter.fit(rest)
            without = rmse(fit[3])
            rest_bic = fitter.bic(fit[2], k - term.size)
            if rest_bic <= bic or len(affected(without, after)) == 0:
                drops.append((float(np.mean(np.square(fit[3] * fitter.w))), i, fit, rest_bic, without))
        if not drops:
            break
        _, i, fit, rest_bic, without = min(drops, key=lambda item: item[0])
        log(f"[diagnose] dropped {terms[i].name} on {named(terms[i].joints, names)} (backward pass): ΔBIC "
            f"{rest_bic - bic:+.1f}, held-out gap {np.round(after, 4).tolist()} → {np.round(without, 4).tolist()}")
        del terms[i]
        theta, inverse, r_tr, r_he = fit
        bic = rest_bic
    return terms, theta, inverse, r_tr, r_he, bic


def contributions(fitter: Fitter, terms: list[Term], r_he: np.ndarray) -> list[dict]:
    """Each term's share: the held-out gap of all terms but that one against all of them."""
    after = rmse(r_he)
    history = []
    for i, term in enumerate(terms):
        before = rmse(fitter.held_out(terms[:i] + terms[i + 1:]))
        joints = affected(before, after)
        red = (1.0 - np.sqrt(np.mean(np.square(after[joints]))) / np.sqrt(np.mean(np.square(before[joints])))
               if len(joints) else 0.0)
        history.append({"affected": joints.tolist(), "gap_reduction": float(red),
                        "held_out_rmse_before": before[joints].tolist(),
                        "held_out_rmse_after": after[joints].tolist()})
    return history


def scored_candidates(fitter: Fitter, terms: Sequence[Term], r_he: np.ndarray, effects: Sequence[str],
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


def greedy(fitter: Fitter, effects: Sequence[str], names: Sequence[str], first_choice: int,
            first_round: list[tuple], log: Callable[[str], None]) -> tuple | None:
    """Forward selection and the backward pass (module docstring, step 2), starting in the first
    round from the acceptable candidate of the ``first_choice``-th distinct effect name (0 = the
    best candidate); None when the first round has fewer acceptable effects. Returns (terms, θ,
    G⁻¹, train and held-out residuals, BIC). The fitter's forced terms are in from the start."""
    terms: list[Term] = list(fitter.forced)
    theta, inverse, r_tr, r_he = fitter.fit(terms)
    bic = fitter.bic(r_tr, sum(t.size for t in terms))
    while True:
        first = len(terms) == len(fitter.forced)
        log(f"[diagnose] round {len(terms) - len(fitter.forced) + 1}: {len(effects) - len(terms)} of {len(effects)} "
            f"effects to try on top of {[t.name for t in terms]}, held-out gap {rmse(r_he).mean():.3f} N·m ...")
        scored = first_round if first else scored_candidates(fitter, terms, r_he, effects, len(names))
        accepted = False
        skip = first_choice if first else 0      # first round: effect names still to pass over
        passed: set[str] = set()
        before = rmse(r_he)
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
            after = rmse(rh)
            joints = affected(before, after)
            problem = inadmissible(fitter, terms, term, th, names)
            if new_bic >= bic or len(joints) == 0 or problem is not None:
                log(f"[diagnose]   rejected {term.name} on {named(term.joints, names)}: ΔBIC {new_bic - bic:+.1f}, "
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
            log(f"[diagnose] accepted {term.name} {dict(term.variant)} on {named(term.joints, names)}: "
                f"held-out gap of {named(joints, names)} −{red:.0%}, ΔBIC {new_bic - old_bic:+.0f}")
            accepted = True
            break
        if not accepted:
            if first and first_choice:
                return None
            break
    return prune(fitter, terms, theta, inverse, r_tr, r_he, bic, log, names)


def select(fitter: Fitter, effects: Sequence[str], names: Sequence[str], log: Callable[[str], None],
           new_load: bool) -> tuple[list[Term], Fit]:
    """The chosen effects and their joint fit: the best of ``STARTS`` greedy runs (the lowest BIC with no more
    effects), refitted under its own priors until every body is consistent, without the joints at a bound of their
    prior; ``new_load`` (against a calibrated model): a payload preferred to link changes that explain no more
    (``payload_first``)."""
    log(f"[diagnose] fitting each of {len(effects)} effects alone (shared by the {STARTS} starts) ...")
    best, best_priors = None, None
    first_round = scored_candidates(fitter, list(fitter.forced), fitter.held_out(list(fitter.forced)), effects,
                                    len(names))    # shared by every start
    initial_priors = dict(fitter.prior_scale)
    for start in range(STARTS):
        fitter.prior_scale = dict(initial_priors)     # every start from the URDF's priors, not the last start's
        found = greedy(fitter, effects, names, start, first_round, lambda line, k=start + 1: log(
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
        log(f"[diagnose] dropped {term.name} on {named(at_bound, names)}: at the bound of its prior "
            f"once fitted with the other effects (another effect seen through it)")
        terms = [*terms[:index], *([Term(term.name, keep, term.variant)] if keep else []), *terms[index + 1:]]
        theta, inverse, r_tr, r_he = consistent(fitter, terms, *fitter.fit(terms))
    if new_load and "payload" in effects:
        terms, (theta, inverse, r_tr, r_he) = payload_first(fitter, terms, (theta, inverse, r_tr, r_he), names, log)
    return terms, (theta, inverse, r_tr, r_he)


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
    worse = affected(rmse(alternative[3]), rmse(fit[3]))      # joints link_inertia explains better
    if len(worse) or inadmissible(fitter, rest, payload, alternative[0], names) is not None:
        fitter.prior_scale = saved
        return terms, fit
    log(f"[diagnose] against a calibrated model: payload instead of link_inertia (the same held-out gap within "
        f"{MIN_REDUCTION:.0%}; one body at the flange is the simpler explanation of a new load)")
    return [*rest, payload], alternative

