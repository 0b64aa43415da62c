"""Physical admissibility of a ``kvark diagnose`` fit: bodies kept physically consistent by tightening their priors,
every effect kept off the bounds of its prior (``gap.priors``), and what the data want beyond a prior
(docs/method.md §8). ROS-free helpers of ``gap.diagnose``.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable, Sequence

import numpy as np

from kvark_ros.core.effect_catalog import BODY_EFFECTS, EFFECTS_BY_NAME, PRIOR_BOUNDED
from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.gap.effects import Priors, Term, theta_split
from kvark_ros.gap.fitting import Fitter

MAX_PRIOR_HALVINGS = 12  # a body's prior σ may shrink 4096-fold toward the URDF before the candidate is refused
BOUND_SHARE = 0.01       # a parameter within 1 % of its prior's range from a bound is "at the bound"
LOAD_RADIUS = 0.02       # m: a load's second moments are pulled toward a solid sphere of this radius at its CoM


def _prior_bounds(term: Term, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
    """A term's bounds of its prior alone: ``Term.bounds`` without the physical ones (θ ≥ 0, the flange link's mass
    > 0), which are not the prior's."""
    lo, hi = term.bounds(priors)
    if EFFECTS_BY_NAME[term.name].nonnegative or term.name == "payload":
        lo = np.full_like(lo, -np.inf)
    return lo, hi


def prior_hits(term: Term, theta: np.ndarray, priors: Priors) -> np.ndarray:
    """Which of a term's parameters θ sit at a bound of its prior (``_prior_bounds``; within ``BOUND_SHARE`` of the
    range)."""
    lo, hi = _prior_bounds(term, priors)
    finite_lo, finite_hi = np.isfinite(lo), np.isfinite(hi)
    span = np.where(finite_lo & finite_hi, hi - np.where(finite_lo, lo, 0.0), np.where(finite_hi, np.abs(hi), 0.0))
    low = finite_lo & (theta <= np.where(finite_lo, lo, 0.0) + BOUND_SHARE * span)
    high = finite_hi & (theta >= np.where(finite_hi, hi, 0.0) - BOUND_SHARE * span)
    return low | high


def prior_use(term: Term, theta: np.ndarray, priors: Priors) -> float | None:
    """The largest share of its prior's bound any of a term's parameters θ uses, |θ| / bound (1: at the bound; above
    1: outside the prior), for the report and the population's check that no effect lies outside its prior without a
    warning (``_prior_bounds``); None for a term without a finite prior bound."""
    lo, hi = _prior_bounds(term, priors)
    upper = np.isfinite(hi) & (hi > 0.0) & (theta > 0.0)
    lower = np.isfinite(lo) & (lo < 0.0) & (theta < 0.0)
    shares = np.concatenate([theta[upper] / hi[upper], theta[lower] / lo[lower]])
    bounded = (np.isfinite(hi) & (hi > 0.0)) | (np.isfinite(lo) & (lo < 0.0))
    if not bounded.any():
        return None
    return float(shares.max()) if shares.size else 0.0


def prior_fields(term: Term, theta: np.ndarray, priors: Priors) -> dict:
    """``diagnosis.json``'s per-effect fields against its prior: ``prior_use`` and ``at_prior_bound`` (any parameter at
    a bound, ``prior_hits``: each such parameter is a warning)."""
    return {"prior_use": prior_use(term, theta, priors), "at_prior_bound": bool(prior_hits(term, theta, priors).any())}


def at_bounds(term: Term, theta: np.ndarray, priors: Priors) -> np.ndarray:
    """Per joint of a per-joint or coupled term (one value for a body term): whether any of its parameters sits at a
    bound of its prior."""
    hits = prior_hits(term, theta, priors)
    if term.name in BODY_EFFECTS:
        return np.array([bool(np.any(hits))])
    return hits.reshape(len(term.joints), -1).any(axis=1)


def _record(fitter: Fitter, term: Term, joints: Sequence[int]) -> None:
    """Remember that ``term`` was dropped at its prior on ``joints`` (−1: a body term), for ``beyond_priors``."""
    variant = tuple(sorted(term.variant.items()))
    fitter.dropped.update((term.name, variant, j) for j in joints)


def without_saturated(fitter: Fitter, terms: Sequence[Term], term: Term, *fit: np.ndarray) -> tuple:
    """A per-joint or coupled candidate without the joints whose θ sits at its prior's bound, refitted (repeatedly,
    until none does); the dropped joints are remembered (``beyond_priors``).

    An effect at the bound is another effect seen through it (a gain on a light wrist joint imitates friction, an
    offset a link's CoM, a large low-order ripple or armature a link's inertia); left in, it would stand for that
    effect with an implausible value and hide real ones on the other joints."""
    while term.name in PRIOR_BOUNDED and term.name not in BODY_EFFECTS:
        pos = sum(t.size for t in terms)
        saturated = at_bounds(term, fit[0][pos:pos + term.size], fitter.priors)
        keep = tuple(j for j, bad in zip(term.joints, saturated) if not bad)
        if keep == term.joints or not keep:
            break
        _record(fitter, term, [j for j in term.joints if j not in keep])
        term = Term(term.name, keep, term.variant)
        fit = fitter.fit([*terms, term])
    return term, fit


def saturated_joints(fitter: Fitter, terms: Sequence[Term], theta: np.ndarray) -> tuple[int, tuple[int, ...]] | None:
    """(term index, joints) of the first term of a joint fit θ with joints at a bound of its prior (a body term: all
    of its joints); ``without_saturated``'s rule, for effects that reached the bound only when later ones joined."""
    pos = 0
    for index, term in enumerate(terms):
        bound = at_bounds(term, theta[pos:pos + term.size], fitter.priors)
        if np.any(bound):
            joints = term.joints if term.name in BODY_EFFECTS else tuple(j for j, hit in zip(term.joints, bound) if hit)
            _record(fitter, term, [-1] if term.name in BODY_EFFECTS else joints)
            return index, joints
        pos += term.size
    return None


def inconsistent_bodies(fitter: Fitter, term: Term, theta: np.ndarray) -> list[tuple[int, str]]:
    """(body index, problem) of every body a payload (index 0) or link_inertia θ makes physically impossible. A
    payload must leave the flange link consistent, and one of positive mass (a tool or load, as the report calls it)
    must be a body itself too (its pseudo-inertia positive semi-definite, Wensing et al. 2018; docs/method.md §8): what
    the report names is what is checked."""
    if term.name == "payload":
        full = term.full_theta(theta)
        problem = inertia_problem(fitter.flange + fitter.flange_map @ full)
        if problem is None and full[0] > 0.0 and (own := inertia_problem(full)) is not None:
            problem = f"the load itself: {own}"
        return [] if problem is None else [(0, problem)]
    if term.name == "link_inertia":
        return [(i, problem) for i, (urdf, change) in enumerate(zip(fitter.links, theta.reshape(-1, 10)))
                if (problem := inertia_problem(urdf + change)) is not None]
    return []


def bad_bodies(fitter: Fitter, terms: Sequence[Term], theta: np.ndarray) -> list[tuple[int, int, str]]:
    """(term index, body index, problem) of every body the payload or link_inertia terms of a joint fit θ make
    physically impossible."""
    bad = []
    for index, (term, own) in enumerate(zip(terms, theta_split(terms, theta))):
        bad += [(index, body, problem) for body, problem in inconsistent_bodies(fitter, term, own)]
    return bad


def point_mass_moments(theta: np.ndarray, radius: float = 0.0) -> np.ndarray:
    """Prior mean (10,) of a payload θ = [m, m c, I about the origin: ixx ixy iyy ixz iyz izz]: zero mass and first
    moments, and the second moments of a point mass m at c, m (|c|² E − c cᵀ), the least inertia a body of that
    mass and centre can have about the origin (a body's inertia about its centre is positive semi-definite); with a
    ``radius`` (m) and a positive mass, those of a solid sphere of that radius instead, (2/5) m r² E more: strictly
    inside the physical set, where a fit pulled toward it lands on a body, not on its boundary."""
    m = float(theta[0])
    com = np.asarray(theta[1:4], dtype=float) / m if m != 0.0 else np.zeros(3)
    inertia = m * (float(com @ com) * np.eye(3) - np.outer(com, com)) + 0.4 * max(m, 0.0) * radius ** 2 * np.eye(3)
    return np.concatenate([np.zeros(4), inertia[[0, 0, 1, 0, 1, 2], [0, 1, 1, 2, 2, 2]]])


def consistent(fitter: Fitter, terms: Sequence[Term], *fit: np.ndarray) -> tuple:
    """A fit of ``terms`` refitted until every body its payload and link_inertia terms change is physically
    consistent: the prior of each offending body is tightened toward the URDF (σ set to ``first_prior`` where it
    was ∞, else halved; at most ``MAX_PRIOR_HALVINGS`` times), a payload's second moments toward those of a solid
    sphere of ``LOAD_RADIUS`` at its fitted mass and centre (``point_mass_moments``: shrinking them toward zero about
    the flange origin would put a massive payload's inertia about its own centre below zero). Returns the last fit
    (check it with ``bad_bodies``).

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
            if name == "payload":      # its second moments pulled toward a point mass of its fitted mass and CoM
                fitter.prior_mean[name] = point_mass_moments(terms[index].full_theta(
                    theta_split(terms, fit[0])[index]), LOAD_RADIUS)
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
    link change must leave its body physically consistent and inside its prior; a per-joint effect must not sit at its
    prior's bound on every joint."""
    pos = sum(t.size for t in terms)
    mine = theta[pos:pos + term.size]
    bad = bad_bodies(fitter, [*terms, term], theta)
    if bad:
        index, body, problem = bad[0]
        name = [*terms, term][index].name
        return f"{'flange link' if name == 'payload' else f'link of {names[body]}'}: {problem}"
    hits = at_bounds(term, mine, fitter.priors)
    if np.all(hits):
        _record(fitter, term, [-1] if term.name in BODY_EFFECTS else term.joints)
        return f"{term.name} at the bound of its prior{'' if term.name in BODY_EFFECTS else ' on every joint'}"
    return None


def beyond_priors(fitter: Fitter, terms: Sequence[Term], gains: Callable[[np.ndarray, np.ndarray], np.ndarray]
                  ) -> list[dict]:
    """Effects the data want beyond their prior, best evidence first: every (effect, variant, joint) dropped at its
    prior during the selection, refitted on top of the final ``terms`` with its prior widened to physics
    (``Priors.physics``: a gain not near zero, an offset within the effort limit; unbounded where physics says
    nothing); kept when its value then lies beyond the prior but inside physics, the BIC improves and ``gains(before,
    after)`` (held-out gap per joint) names a joint. A value at the physical bound is not that effect: it is not
    offered. One record per effect and joint, its largest held-out gain: effect, joint (−1: body), wanted |θ|, bound,
    their ratio, held-out gap before/after of the joints it helps, ΔBIC. Ordered by how much of the held-out gap
    each explains (N·m summed over the joints it helps; then the BIC), whatever its ratio: the report leads with the
    explanation that explains most; a weaker record on the same joints goes to the stronger one's ``look_alikes``."""
    base = fitter.fit(list(terms))
    k = sum(t.size for t in terms)
    bic = fitter.bic(base[2], k)
    before = np.sqrt(np.mean(np.square(base[3]), axis=0))
    present = {(t.name, tuple(sorted(t.variant.items())), j) for t in terms for j in (
        (-1,) if t.name in BODY_EFFECTS else t.joints)}
    found: dict[tuple[str, int], dict] = {}
    priors = fitter.priors
    for name, variant, joint in sorted(fitter.dropped - present):
        probe = Term(name, tuple(range(fitter.n)) if joint < 0 else (joint,), dict(variant))
        limit = np.asarray(priors.limit(name), dtype=float)
        physical = np.broadcast_to(np.asarray(priors.physics.get(name, np.inf), dtype=float), limit.shape)
        fitter.priors = replace(priors, limits={**priors.limits, name: physical.copy()})
        try:
            theta, _, r_tr, r_he = fitter.fit([*terms, probe])
            wide_hi = probe.bounds(fitter.priors)[1]
        finally:
            fitter.priors = priors
        mine = theta[k:k + probe.size]
        lo, hi = probe.bounds(priors)
        over = np.maximum(mine - hi, -np.inf if EFFECTS_BY_NAME[name].nonnegative else lo - mine)
        edge = np.where(np.isfinite(wide_hi), (1.0 - BOUND_SHARE) * wide_hi, np.inf)    # within 1 % of physics
        at_physics = (mine >= edge) | ((not EFFECTS_BY_NAME[name].nonnegative) & (mine <= -edge))
        if name == "payload":
            over, at_physics = over[:1], at_physics[:1]
        after = np.sqrt(np.mean(np.square(r_he), axis=0))
        helped = gains(before, after)
        new_bic = fitter.bic(r_tr, k + probe.size)
        if not np.any(over > 0.0) or np.any(at_physics) or len(helped) == 0 or new_bic >= bic:
            continue
        worst = int(np.argmax(over))
        record = {"effect": name, "variant": dict(variant), "joint": joint, "wanted": float(abs(mine[worst])),
                  "bound": float(hi[worst]), "ratio": float(abs(mine[worst]) / hi[worst]),
                  "joints_helped": [int(j) for j in helped],
                  "held_out_before": before[helped].tolist(), "held_out_after": after[helped].tolist(),
                  "explained": float(np.sum(before[helped] - after[helped])), "delta_bic": float(new_bic - bic)}
        key = (name, joint)
        if key not in found or record["explained"] > found[key]["explained"]:
            found[key] = record
    kept: list[dict] = []
    for record in sorted(found.values(), key=lambda item: (-item["explained"], item["delta_bic"])):
        better = next((other for other in kept if set(record["joints_helped"]) <= set(other["joints_helped"])), None)
        if better is None:
            kept.append({**record, "look_alikes": []})
        else:
            better["look_alikes"].append(record)
    return kept
