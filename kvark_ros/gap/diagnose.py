"""``kvark diagnose``: where the nominal model and the measured data disagree, in physical terms.

1. the gap ``τ_m − τ_EL`` per joint on the recorded motion (q̈ and τ_m through the same
   Savitzky-Golay filter as ``kvark train``);
2. greedy forward selection over the named effects of ``kvark_ros.gap.effects``: samples are split
   in time (the last ``holdout`` share of every recording is held out); each round every
   (effect, joint set) candidate is fitted on the training part by bounded least squares
   (positive friction, armature and payload mass), the one that lowers the held-out gap most is
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
   a run that trades one look-alike for the right effect ends with fewer of them). Each remaining
   effect's reported reduction is the held-out gap of all effects but that one against all of them;
3. writes ``diagnosis.json``, ``augmentation.yaml`` (the accepted effects, loadable by
   ``effects.augmentation_gap``), ``report.md`` and plots.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import yaml
from scipy.optimize import lsq_linear

from kvark_ros.core.augmentation import load_augmentation
from kvark_ros.core.config import EstimatorConfig, load_config
from kvark_ros.core.files import write_text_atomically
from kvark_ros.core.inputs import EstimatorInputs
from kvark_ros.core.linalg import single_threaded_blas
from kvark_ros.core.model_store import TrainedModel, save_model
from kvark_ros.core.robot_model import RobotModel
from kvark_ros.core.training import SAVGOL_WINDOW, smoothed_signals, train_model
from kvark_ros.gap.effects import (
    EFFECT_NAMES,
    MAX_GAIN_ERROR,
    PER_JOINT,
    Signals,
    Term,
    payload_parameters,
    physical_parameters,
    signals,
    variants,
)
from kvark_ros.io.alignment import load_recordings

HOLDOUT = 0.3            # share of every recording (its end) held out
MIN_REDUCTION = 0.05     # an effect must cut the held-out gap of its joints by ≥ 5 %
MIN_ABS_REDUCTION = 0.005  # N·m, and by at least this much (filter noise floor)
DECIMATE_DT = 0.008      # s, sample spacing after smoothing (the filter passes far less than 60 Hz)
SCREEN_TOP = 4           # candidates refitted jointly per round
STARTS = 3               # greedy runs, each from another acceptable first effect (see module docstring)


@dataclass
class Diagnosis:
    """Result of ``diagnose``: the JSON document, the accepted terms and their raw θ, and the
    held-out signals with the gap before/after (for plots)."""

    result: dict
    terms: list[Term]
    theta: list[np.ndarray]
    held: Signals
    held_after: np.ndarray


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


class _Fitter:
    """Bounded weighted least squares of the gap on a set of terms."""

    def __init__(self, train: Signals, held: Signals, weights: np.ndarray) -> None:
        self.train, self.held, self.w = train, held, weights
        self.t, self.n = train.gap.shape
        self._cache: dict = {}

    def design(self, term: Term) -> tuple[np.ndarray, np.ndarray]:
        """(train, held-out) regressor blocks of a term, cached."""
        key = (term.name, term.joints, tuple(sorted(term.variant.items())))
        if key not in self._cache:
            self._cache[key] = (term.design(self.train), term.design(self.held))
        return self._cache[key]

    def fit(self, terms: Sequence[Term]) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """(θ, covariance, train residual, held-out residual)."""
        if not terms:
            return np.zeros(0), None, self.train.gap.copy(), self.held.gap.copy()
        blocks = [self.design(term) for term in terms]
        a_tr = np.concatenate([b[0] for b in blocks], axis=2)
        a_he = np.concatenate([b[1] for b in blocks], axis=2)
        lo = np.concatenate([term.bounds()[0] for term in terms])
        hi = np.concatenate([term.bounds()[1] for term in terms])
        a = (a_tr * self.w[None, :, None]).reshape(-1, a_tr.shape[2])
        b = (self.train.gap * self.w).reshape(-1)
        scale = np.sqrt(np.mean(np.square(a), axis=0)) + 1e-12       # column scaling for conditioning
        q_mat, r_mat = np.linalg.qr(a / scale)      # same minimiser, a p × p problem for BVLS
        sol = lsq_linear(r_mat, q_mat.T @ b, bounds=(lo * scale, hi * scale), method="bvls")
        theta = sol.x / scale
        r_tr = self.train.gap - a_tr @ theta
        r_he = self.held.gap - a_he @ theta
        dof = max(1, a.shape[0] - a.shape[1])
        sigma2 = float(np.sum(np.square(r_tr * self.w))) / dof
        an = a / scale
        cov = sigma2 * np.linalg.pinv(an.T @ an) / np.outer(scale, scale)
        return theta, cov, r_tr, r_he

    def bic(self, r_tr: np.ndarray, k: int) -> float:
        mse = np.maximum(np.mean(np.square(r_tr), axis=0), 1e-12)
        return float(self.t * np.sum(np.log(mse)) + k * np.log(self.t * self.n))


def _screen(name: str, variant: dict, fitter: _Fitter, terms: Sequence[Term], r_he: np.ndarray,
            n: int) -> Term | None:
    """Candidate joint set of one effect variant: the payload acts on every joint, a coupled effect
    is screened by ``_screen_coupled``, a per-joint effect keeps the joints whose held-out gap
    drops enough when it is added on that joint alone and everything is refitted."""
    if name == "payload":
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


def _screen_coupled(name: str, variant: dict, fitter: _Fitter, terms: Sequence[Term], n: int) -> Term | None:
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


def _without_saturated_gains(fitter: _Fitter, terms: Sequence[Term], term: Term, *fit: np.ndarray) -> tuple:
    """A drive-gain candidate without the joints whose gain error sits at its bound, refitted.

    A gain at the bound is another effect seen through τ_m (on a light wrist joint τ_m is mostly
    friction); left in, it would make the whole candidate inadmissible and hide real gain errors on
    the other joints."""
    pos = sum(t.size for t in terms)
    gains = fit[0][pos:pos + term.size]
    keep = tuple(j for j, g in zip(term.joints, gains) if abs(g) < 0.99 * MAX_GAIN_ERROR)
    if keep == term.joints or not keep:
        return term, fit
    reduced = Term(term.name, keep, term.variant)
    return reduced, fitter.fit([*terms, reduced])


def _affected(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Joints whose held-out gap drops by ≥ MIN_REDUCTION (relative) and MIN_ABS_REDUCTION."""
    drop = before - after
    return np.flatnonzero((drop >= MIN_REDUCTION * before) & (drop >= MIN_ABS_REDUCTION))


def _prune(fitter: _Fitter, terms: list[Term], theta: np.ndarray, cov: np.ndarray | None, r_tr: np.ndarray,
           r_he: np.ndarray, bic: float, log: Callable[[str], None]) -> tuple:
    """Backward pass over the accepted terms (module docstring, step 2): (terms, θ, covariance,
    train and held-out residuals, BIC)."""
    terms = list(terms)
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
        log(f"[diagnose] dropped {terms[i].name} {list(terms[i].joints)} (backward pass): ΔBIC "
            f"{rest_bic - bic:+.1f}, held-out gap {np.round(after, 4).tolist()} → {np.round(without, 4).tolist()}")
        del terms[i]
        theta, cov, r_tr, r_he = fit
        bic = rest_bic
    return terms, theta, cov, r_tr, r_he, bic


def _contributions(fitter: _Fitter, terms: list[Term], r_he: np.ndarray) -> list[dict]:
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


def _scored_candidates(fitter: _Fitter, terms: Sequence[Term], r_he: np.ndarray, effects: Sequence[str],
                       n: int) -> list[tuple]:
    """Every screened candidate added to ``terms`` and fitted: (weighted held-out error, term, fit),
    best first."""
    used = {t.name for t in terms}
    scored = []
    for name in effects:
        if name in used:
            continue
        for variant in variants(name):
            term = _screen(name, variant, fitter, terms, r_he, n)
            if term is not None:
                fit = fitter.fit([*terms, term])
                scored.append((float(np.mean(np.square(fit[3] * fitter.w))), term, fit))
    scored.sort(key=lambda item: item[0])
    return scored


def _greedy(fitter: _Fitter, effects: Sequence[str], n: int, first_choice: int, first_round: list[tuple],
            log: Callable[[str], None]) -> tuple | None:
    """Forward selection and the backward pass (module docstring, step 2), starting in the first
    round from the acceptable candidate of the ``first_choice``-th distinct effect name (0 = the
    best candidate); None when the first round has fewer acceptable effects. Returns (terms, θ,
    covariance, train and held-out residuals, BIC)."""
    terms: list[Term] = []
    theta, cov, r_tr, r_he = fitter.fit(terms)
    bic = fitter.bic(r_tr, 0)
    while True:
        scored = first_round if not terms else _scored_candidates(fitter, terms, r_he, effects, n)
        accepted = False
        skip = first_choice if not terms else 0      # first round: effect names still to pass over
        passed: set[str] = set()
        before = _rmse(r_he)
        for score, term, (th, cv, rt, rh) in (scored if skip else scored[:SCREEN_TOP]):
            if term.name in passed:
                continue
            if term.name == "drive_gain":
                term, (th, cv, rt, rh) = _without_saturated_gains(fitter, terms, term, th, cv, rt, rh)
            k = sum(t.size for t in terms) + term.size
            new_bic = fitter.bic(rt, k)
            after = _rmse(rh)
            joints = _affected(before, after)
            physical = True
            if term.name == "payload":
                pos = sum(t.size for t in terms)
                physical = payload_parameters(th[pos:pos + term.size], None)[0]["physically_consistent"]
            elif term.name == "drive_gain":   # a gain error at its bound is another effect seen through τ_m
                pos = sum(t.size for t in terms)
                physical = bool(np.all(np.abs(th[pos:pos + term.size]) < 0.99 * MAX_GAIN_ERROR))
            if new_bic >= bic or len(joints) == 0 or not physical:
                log(f"[diagnose]   rejected {term.name} {list(term.joints)}: ΔBIC {new_bic - bic:+.1f}, "
                    f"{'' if physical else 'not physically admissible, '}"
                    f"held-out gap {np.round(before, 4).tolist()} → {np.round(after, 4).tolist()}")
                continue
            if skip:
                skip -= 1
                passed.add(term.name)
                continue
            red = 1.0 - np.sqrt(np.mean(np.square(after[joints]))) / np.sqrt(np.mean(np.square(before[joints])))
            terms.append(term)
            old_bic = bic
            theta, cov, r_tr, r_he, bic = th, cv, rt, rh, new_bic
            log(f"[diagnose] accepted {term.name} {dict(term.variant)} on joints {list(term.joints)}: "
                f"held-out gap of joints {joints.tolist()} −{red:.0%}, ΔBIC {new_bic - old_bic:+.0f}")
            accepted = True
            break
        if not accepted:
            if not terms and first_choice:
                return None
            break
    return _prune(fitter, terms, theta, cov, r_tr, r_he, bic, log)


def diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float = HOLDOUT,
             effects: Sequence[str] = EFFECT_NAMES, log: Callable[[str], None] = print) -> Diagnosis:
    """Greedy selection of named effects explaining the gap (see module docstring)."""
    with single_threaded_blas():  # hundreds of small least-squares fits
        return _diagnose(robot, segments, holdout, effects, log)


def _diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float,
              effects: Sequence[str], log: Callable[[str], None]) -> Diagnosis:
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
    weights = 1.0 / np.maximum(_rmse(train.gap), 0.01)
    fitter = _Fitter(train, held, weights)
    log(f"[diagnose] held-out gap per joint before: {np.round(gap_before, 4).tolist()} N·m")
    best = None
    first_round = _scored_candidates(fitter, [], held.gap, effects, n)    # shared by every start
    for start in range(STARTS):
        found = _greedy(fitter, effects, n, start, first_round, lambda line, k=start + 1: log(
            line.replace("[diagnose]", f"[diagnose] start {k}:")))
        if found is None:
            break
        score = float(np.sqrt(np.mean(np.square(found[4] * fitter.w))))
        log(f"[diagnose] start {start + 1}: {[t.name for t in found[0]]}, BIC {found[-1]:.0f}, "
            f"weighted held-out gap {score:.4f}")
        if best is None or (found[-1] < best[-1] and len(found[0]) <= len(best[0])):
            best = found
    terms, theta, cov, _, r_he, _ = best
    history = _contributions(fitter, terms, r_he)
    gap_after = _rmse(r_he)
    result_effects, thetas = [], []
    pos = 0
    for term, info in zip(terms, history):
        th = theta[pos:pos + term.size]
        cv = None if cov is None else cov[pos:pos + term.size, pos:pos + term.size]
        pos += term.size
        params, ci = physical_parameters(term, th, cv)
        joints = list(term.joints) if term.name != "payload" else info["affected"]
        result_effects.append({"name": term.name, "joints": [int(j) for j in joints], "parameters": params,
                               "ci95": ci, "gap_reduction": info["gap_reduction"],
                               "held_out_rmse_before": info["held_out_rmse_before"],
                               "held_out_rmse_after": info["held_out_rmse_after"]})
        thetas.append(th)
    result = {
        "robot_joint_names": list(robot.joint_names),
        "gap_before": {"joint_rmse": gap_before.tolist(), "joint_rmse_mean": float(gap_before.mean())},
        "gap_after": {"joint_rmse": gap_after.tolist(), "joint_rmse_mean": float(gap_after.mean())},
        "effects": result_effects,
        "holdout": holdout, "samples": {"train": len(train), "held_out": len(held)},
        "seconds": round(time.perf_counter() - started, 1),
    }
    log(f"[diagnose] held-out gap per joint after: {np.round(gap_after, 4).tolist()} N·m "
        f"(mean {gap_before.mean():.4f} → {gap_after.mean():.4f})")
    return Diagnosis(result, terms, thetas, held, r_he)


def augmentation(diag: Diagnosis, robot: RobotModel, robot_name: str = "") -> dict:
    """The accepted effects as a plain mapping (``augmentation.yaml``)."""
    entries = []
    for term, th, eff in zip(diag.terms, diag.theta, diag.result["effects"]):
        entries.append({"name": term.name, "joint_indices": [int(j) for j in term.joints],
                        "joints": [robot.joint_names[j] for j in term.joints],
                        "variant": {k: float(v) for k, v in term.variant.items()},
                        "parameters": eff["parameters"], "theta": [float(v) for v in th]})
    return {"robot": robot_name, "joint_names": list(robot.joint_names),
            "convention": "tau_m - tau_EL = sum over effects of design(q, qd, qdd, tau_m) @ theta "
                          "(kvark_ros.gap.effects.augmentation_gap)",
            "effects": entries}


def train_on_diagnosis(config: EstimatorConfig, robot: RobotModel, segments: Sequence[EstimatorInputs], out: Path,
                       baselines: bool, seed: int = 0,
                       log: Callable[[str], None] = print) -> tuple[TrainedModel, dict]:
    """Diagnose ``segments`` on ``robot`` (the nominal model), write the outputs to ``out/diagnosis``, train on
    the model augmented with what was named and save it to ``out/model_augmented``.

    Returns the trained model and a summary: the effects and the mean held-out gap before/after (N·m).
    """
    diagnosis = diagnose(robot, segments, log=log)
    write_outputs(diagnosis, robot, out / "diagnosis", config.robot, log=log)
    augmentation = load_augmentation(out / "diagnosis" / "augmentation.yaml", config.joint_names)
    trained = train_model(RobotModel.from_config(config, augmentation), config.robot, segments, baselines=baselines,
                          seed=seed, log=log)
    save_model(out / "model_augmented", trained)
    return trained, {"effects": list(augmentation.effect_names),
                     "gap_before": diagnosis.result["gap_before"]["joint_rmse_mean"],
                     "gap_after": diagnosis.result["gap_after"]["joint_rmse_mean"]}


def write_outputs(diag: Diagnosis, robot: RobotModel, out: Path, robot_name: str = "", plots: bool = True,
                  log: Callable[[str], None] = print) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "diagnosis.json", out / "augmentation.yaml", out / "report.md"]
    write_text_atomically(paths[0], json.dumps(diag.result, indent=2))
    write_text_atomically(paths[1], yaml.safe_dump(augmentation(diag, robot, robot_name), sort_keys=False))
    write_text_atomically(paths[2], report(diag, robot))
    if plots:
        paths.extend(plot(diag, robot, out))
    for path in paths:
        log(f"[diagnose] wrote {path}")
    return paths


def report(diag: Diagnosis, robot: RobotModel) -> str:
    r = diag.result
    lines = ["# Model-gap diagnosis", "",
             f"Held-out samples: {r['samples']['held_out']} (last {r['holdout']:.0%} of each recording).", "",
             "| joint | gap before (N·m) | gap after (N·m) | reduction |", "|---|---|---|---|"]
    for j, name in enumerate(robot.joint_names):
        b, a = r["gap_before"]["joint_rmse"][j], r["gap_after"]["joint_rmse"][j]
        lines.append(f"| {name} | {b:.4f} | {a:.4f} | {1 - a / b if b > 0 else 0:.0%} |")
    lines += [f"| mean | {r['gap_before']['joint_rmse_mean']:.4f} | {r['gap_after']['joint_rmse_mean']:.4f} | |",
              "", "## Effects found", ""]
    if not r["effects"]:
        lines.append("None: the nominal model explains the data to within the noise.")
    for eff in r["effects"]:
        lines.append(f"- **{eff['name']}** on joints {[robot.joint_names[j] for j in eff['joints']]}: "
                     f"held-out gap of those joints −{eff['gap_reduction']:.0%}")
        lines.append(f"  - parameters: `{json.dumps(eff['parameters'])}`")
        lines.append(f"  - 95 % half-widths (least-squares covariance; samples are correlated, so "
                     f"optimistic): `{json.dumps(eff['ci95'])}`")
    lines += ["", "Plots: `gap_per_joint.png`, `residual_vs_velocity.png`, `residual_vs_position.png`.", ""]
    return "\n".join(lines)


def plot(diag: Diagnosis, robot: RobotModel, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r, n = diag.result, robot.n
    paths = []
    fig, ax = plt.subplots(figsize=(1.2 * n + 3, 3.5))
    x = np.arange(n)
    ax.bar(x - 0.2, r["gap_before"]["joint_rmse"], 0.4, label="before")
    ax.bar(x + 0.2, r["gap_after"]["joint_rmse"], 0.4, label="after")
    ax.set_xticks(x, [str(j + 1) for j in x])
    ax.set_xlabel("joint")
    ax.set_ylabel("held-out gap RMSE (N·m)")
    ax.legend()
    fig.tight_layout()
    paths.append(out / "gap_per_joint.png")
    fig.savefig(paths[-1], dpi=90)
    plt.close(fig)
    for key, label, values in (("velocity", "q̇ (rad/s)", diag.held.qd), ("position", "q (rad)", diag.held.q)):
        cols = 4 if n > 6 else 3
        rows = int(np.ceil(n / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
        for j, axj in enumerate(axes.flat):
            if j >= n:
                axj.set_visible(False)
                continue
            axj.scatter(values[:, j], diag.held.gap[:, j], s=2, alpha=0.4, label="before")
            axj.scatter(values[:, j], diag.held_after[:, j], s=2, alpha=0.4, label="after")
            axj.set_title(robot.joint_names[j], fontsize=9)
            axj.set_xlabel(label)
            axj.set_ylabel("gap (N·m)")
        axes.flat[0].legend(markerscale=4)
        fig.tight_layout()
        paths.append(out / f"residual_vs_{key}.png")
        fig.savefig(paths[-1], dpi=80)
        plt.close(fig)
    return paths


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "diagnose", help="name the physical effects the nominal model lacks, from contact-free bags",
        description="Compute the gap τ_m − τ_EL between the commanded torque and the nominal model on "
                    "contact-free bags, select named physical effects (friction, armature, payload, drive "
                    "gain, torque offset, ripple, joint offset) greedily on held-out data, and write "
                    "diagnosis.json, augmentation.yaml, report.md and plots.")
    parser.add_argument("--config", required=True, help="estimator config YAML (e.g. config/panda.yaml)")
    parser.add_argument("--bags", nargs="+", required=True, metavar="BAG", help="contact-free bags")
    parser.add_argument("--holdout", type=float, default=HOLDOUT,
                        help="share of every recording (its end) held out for selection (default 0.3)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--no-plots", action="store_true", help="do not write plots")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    robot = RobotModel.from_config(config)
    segments = load_recordings(args.bags, config.joint_names, config.input.command_max_age, "diagnose")
    log = lambda line: print(line, flush=True)   # noqa: E731
    diag = diagnose(robot, segments, args.holdout, log=log)
    write_outputs(diag, robot, Path(args.out), config.robot, plots=not args.no_plots, log=log)
    return 0
