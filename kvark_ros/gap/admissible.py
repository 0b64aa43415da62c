"""Physical admissibility of a ``kvark diagnose`` fit: bodies kept physically consistent by tightening their priors,
drive gains and joint offsets kept off the bounds of theirs (docs/method.md §8). ROS-free helpers of ``gap.diagnose``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from kvark_ros.core.effect_catalog import PRIOR_BOUNDED
from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.gap.effects import Priors, Term
from kvark_ros.gap.fitting import Fitter

MAX_PRIOR_HALVINGS = 12  # a body's prior σ may shrink 4096-fold toward the URDF before the candidate is refused


def at_bounds(term: Term, theta: np.ndarray, priors: Priors) -> np.ndarray:
    """Which of a drive-gain or joint-offset term's joints sit at a bound of ``priors`` (within 1 %)."""
    lo, hi = term.bounds(priors)
    span = hi - lo
    return (theta <= lo + 0.01 * span) | (theta >= hi - 0.01 * span)


def without_saturated(fitter: Fitter, terms: Sequence[Term], term: Term, *fit: np.ndarray) -> tuple:
    """A drive-gain or joint-offset candidate (``PRIOR_BOUNDED``) without the joints whose θ sits at its prior's bound,
    refitted (repeatedly, until none does).

    A gain or offset at the bound is another effect seen through τ_m or through gravity (on a light wrist joint
    τ_m is mostly friction; a heavier link looks like an encoder offset); left in, it would stand for that
    effect with an implausible value and hide real gains or offsets on the other joints."""
    while term.name in PRIOR_BOUNDED:
        pos = sum(t.size for t in terms)
        saturated = at_bounds(term, fit[0][pos:pos + term.size], fitter.priors)
        keep = tuple(j for j, bad in zip(term.joints, saturated) if not bad)
        if keep == term.joints or not keep:
            break
        term = Term(term.name, keep, term.variant)
        fit = fitter.fit([*terms, term])
    return term, fit


def saturated_joints(fitter: Fitter, terms: Sequence[Term], theta: np.ndarray) -> tuple[int, tuple[int, ...]] | None:
    """(term index, joints) of the first drive-gain or joint-offset term of a joint fit θ with joints at a bound of
    its prior (``without_saturated``'s rule, for effects that reached the bound only when later ones joined)."""
    pos = 0
    for index, term in enumerate(terms):
        if term.name in PRIOR_BOUNDED:
            bound = at_bounds(term, theta[pos:pos + term.size], fitter.priors)
            if np.any(bound):
                return index, tuple(j for j, hit in zip(term.joints, bound) if hit)
        pos += term.size
    return None


def inconsistent_bodies(fitter: Fitter, term: Term, theta: np.ndarray) -> list[tuple[int, str]]:
    """(body index, problem) of every body a payload (index 0) or link_inertia θ makes physically impossible."""
    if term.name == "payload":
        problem = inertia_problem(fitter.flange + fitter.flange_map @ term.full_theta(theta))
        return [] if problem is None else [(0, problem)]
    if term.name == "link_inertia":
        return [(i, problem) for i, (urdf, change) in enumerate(zip(fitter.links, theta.reshape(-1, 10)))
                if (problem := inertia_problem(urdf + change)) is not None]
    return []


def bad_bodies(fitter: Fitter, terms: Sequence[Term], theta: np.ndarray) -> list[tuple[int, int, str]]:
    """(term index, body index, problem) of every body the payload or link_inertia terms of a joint fit θ make
    physically impossible."""
    bad, pos = [], 0
    for index, term in enumerate(terms):
        found = inconsistent_bodies(fitter, term, theta[pos:pos + term.size])
        bad += [(index, body, problem) for body, problem in found]
        pos += term.size
    return bad


def consistent(fitter: Fitter, terms: Sequence[Term], *fit: np.ndarray) -> tuple:
    """A fit of ``terms`` refitted until every body its payload and link_inertia terms change is physically
    consistent: the prior of each offending body is tightened toward the URDF (σ set to ``first_prior`` where it
    was ∞, else halved; at most ``MAX_PRIOR_HALVINGS`` times). Returns the last fit (check it with ``bad_bodies``).

    The data identify only some combinations of a link's parameters (a base link turning about z shows only
    its I_zz); the others follow the prior, and a prior loose enough for the identified ones can let them
    leave the physical set, also when a later effect is fitted jointly with them. Tightening only the
    offending bodies keeps the identified parameters free elsewhere.
    """
    for _ in range(MAX_PRIOR_HALVINGS):
        bad = bad_bodies(fitter, terms, fit[0])
        if not bad:
            break
        for index, body, _ in bad:
            name = terms[index].name
            scale = fitter.prior_scale[name].copy()
            block = slice(0, 10) if name == "payload" else slice(10 * body, 10 * body + 10)
            first = fitter.first_prior[name][block]
            # halved where finite; where ∞, the first prior (which may itself be ∞: that parameter stays free)
            scale[block] = np.where(np.isfinite(scale[block]), 0.5 * scale[block], first)
            fitter.prior_scale[name] = scale
        fit = fitter.fit(list(terms))
    return fit


def inadmissible(fitter: Fitter, terms: Sequence[Term], term: Term, theta: np.ndarray,
                 names: Sequence[str]) -> str | None:
    """Why a fitted candidate (added to ``terms``) is physically impossible, or None: every payload/tool and
    link change must leave its body physically consistent; a drive gain or joint offset must not sit at its
    prior's bound."""
    pos = sum(t.size for t in terms)
    mine = theta[pos:pos + term.size]
    bad = bad_bodies(fitter, [*terms, term], theta)
    if bad:
        index, body, problem = bad[0]
        name = [*terms, term][index].name
        return f"{'flange link' if name == 'payload' else f'link of {names[body]}'}: {problem}"
    if term.name in PRIOR_BOUNDED and np.all(at_bounds(term, mine, fitter.priors)):
        return f"{term.name} at the bound of its prior on every joint"
    return None
