"""``kvark diagnose``'s outputs: ``diagnosis.json``, ``augmentation.yaml``, ``report.md`` (gap tables on filtered
and raw signals, priors, warnings, look-alikes, the effects with their parameters) and the plots
(``gap.diagnosis_plots``)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from kvark_ros.core.files import write_text_atomically
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.effects import Signals, Term
from kvark_ros.gap.known_load import gain_cells


@dataclass
class Diagnosis:
    """Result of ``diagnose``: the JSON document, the accepted terms and their raw θ, and the
    held-out signals with the gap before/after (for plots), ``sample_interval`` s apart (None: unknown);
    ``relative_to``: the model the result is relative to where it is not the one diagnosed (a known-load
    calibration: the robot with the drive gains it measured), None where it is."""

    result: dict
    terms: list[Term]
    theta: list[np.ndarray]
    held: Signals
    held_after: np.ndarray
    sample_interval: float | None = None
    relative_to: RobotModel | None = None


def report(diag: Diagnosis, robot: RobotModel) -> str:
    r = diag.result
    lines = ["# Model-gap diagnosis", "",
             f"Held-out samples: {r['samples']['held_out']} (last {r['holdout']:.0%} of each recording).", "",
             *([f"Relative to the model augmented by `{r['against']}`: the effects below are "
                + ("the rest, selected on the free-motion recordings alone" if r.get("known_load_calibration")
                   else "what changed since") + f", chosen from {', '.join(r['library'])}; augmentation.yaml holds "
                f"both.", ""] if r.get("against") else []),
             f"Gap RMSE on the selection's signals ({r['gap_filtering']}) and on raw signals "
             f"({r['gap_raw'].get('filter', 'none')}), which published identification figures use.", "",
             "| joint | gap before (N·m) | gap after (N·m) | reduction | raw before | raw after |",
             "|---|---|---|---|---|---|"]
    raw = r["gap_raw"]
    for j, name in enumerate(robot.joint_names):
        b, a = r["gap_before"]["joint_rmse"][j], r["gap_after"]["joint_rmse"][j]
        raw_cells = f"{raw['before'][j]:.4f} | {raw['after'][j]:.4f}" if raw["before"] else "– | –"
        lines.append(f"| {name} | {b:.4f} | {a:.4f} | {1 - a / b if b > 0 else 0:.0%} | {raw_cells} |")
    lines += [f"| mean | {r['gap_before']['joint_rmse_mean']:.4f} | {r['gap_after']['joint_rmse_mean']:.4f} | | "
              f"{raw['before_mean']:.4f} | {raw['after_mean']:.4f} |", "", "## Warnings", "",
              *(["What the data want beyond a prior comes first, the explanation that explains most of the held-out "
                 "gap first" + ("; a drive gain the fit with the known load wanted beyond its prior before them"
                                if r.get("known_load_calibration") else "")
                 + "; then the parameters at a bound of their prior.", ""] if r["warnings"] else [])]
    lines += [f"- {warning}" for warning in r["warnings"]] or [
        "None: no parameter sits at a bound of its prior, and no effect wants a value beyond it."]
    lines += ["", *drive_gains_section(r["drive_gains"], robot.joint_names), "", *_priors_table(r["priors"])]
    lines += ["", "## Look-alikes", "",
              "Effects whose regressors are nearly collinear on this motion (cosine of the smallest principal angle "
              "≥ 0.95): the data alone do not tell them apart; the accepted one won on BIC, held-out gap and priors.",
              ""]
    lines += [f"- {pair['accepted']} ~ {pair['look_alike']} (cosine {pair['cosine']:.3f})"
              for pair in r.get("look_alikes", [])] or ["None."]
    regrouping = r.get("flange_mass")
    if regrouping and not regrouping["identified"]:
        lines += ["", f"The flange link's mass is not identified on its own: a mass at the flange is exactly a "
                  f"change of the inertial parameters of {regrouping['link_before_flange']} (relative residual "
                  f"{regrouping['relative_residual']:.0e} on this motion; the base-parameter regrouping of "
                  "identification). A tool's or payload's mass change is read relative to that link's URDF values, "
                  "and link_inertia can absorb it: an error of that link's mass shifts the tool's by as much."]
    lines += ["", "## Effects found", ""]
    if not r["effects"]:
        lines.append("None: the nominal model explains the data to within the noise.")
    for eff in r["effects"]:
        if eff["name"] == "payload":
            lines += _payload_lines(eff)
        use = eff.get("prior_use")
        lines.append(f"- **{eff['name']}** on joints {[robot.joint_names[j] for j in eff['joints']]}: "
                     f"held-out gap of those joints −{eff['gap_reduction']:.0%}"
                     + ("" if use is None else f"; uses {use:.0%} of its prior (the largest |value| / bound)"))
        lines.append(f"  - parameters: `{json.dumps(eff['parameters'])}`")
        lines.append(f"  - 95 % half-widths (least squares with the residuals' correlation in time; a payload's mass "
                     f"also carries the drive gains' intervals; docs/method.md §8.3): `{json.dumps(eff['ci95'])}`")
    lines += ["", "Plots, on the held-out samples: `gap_per_joint.png` (gap RMSE per joint before and after), "
              "`gap_over_time.png` (the gap τ_m − τ_EL over time per joint, before and after), "
              + ("`effect_contributions.png` (each effect's torque, RMS per joint, beside the gap), "
                 if r["effects"] else "")
              + "`residual_vs_velocity.png` and `residual_vs_position.png` (the gap against q̇ and q).", ""]
    return "\n".join(lines)


def _payload_lines(effect: dict) -> list[str]:
    """A payload's lines in the effects list: what it is, its mass with the 95 % half-width (the gains' share said),
    and each consistency claim as checked (``plausibility.flange_change``)."""
    params, width = effect["parameters"], effect["ci95"].get("mass")
    gains = params.get("mass_gain_ci95")
    lines = [f"- **{params['kind']}**: mass change {params['mass_change']:+.3f}"
             f"{'' if width is None else f' ± {width:.3f}'} kg (95 %"
             + ("" if gains is None else f", of which ±{gains:.3f} kg from the drive gains") + "; flange link "
             f"{params['flange_link_mass_urdf']:.3f} → {params['flange_link_mass_total']:.3f} kg, "
             f"{'physically consistent' if params['flange_link_consistent'] else 'NOT physically consistent'})"]
    if params.get("payload_consistent") is not None:
        eigen = ", ".join(f"{v:.2g}" for v in params["inertia_eigenvalues"])
        lines.append(f"  - as a body of its own: {'consistent' if params['payload_consistent'] else 'NOT consistent'} "
                     f"(principal moments about its centre {eigen} kg·m²)")
    return lines


def drive_gains_section(gains: dict, joint_names: Sequence[str]) -> list[str]:
    """report.md's drive gains: measured against a known load (each with its 95 % interval, and what the calibration
    read of the load), or unidentified, with how far they may move a payload's mass."""
    lines = ["## Drive gains", ""]
    load, bound = gains.get("calibrated_with"), gains["prior"]
    if load is None:
        named = ", ".join(f"{name} {g:.3f}" for name, g in zip(joint_names, gains["gain"]) if g != 1.0)
        return lines + [
            ("" if not named else f"Named by the fit: {named}. ")
            + f"Unidentified: τ_m is {gains['torque_measurement']}, and free motion cannot tell a drive gain from the "
            f"links' inertia (they look alike). A gain error within the prior |1 − g| ≤ {bound:.0%} scales a "
            f"payload's torque one to one, so a payload's mass read with this model may be off by up to "
            f"±{gains['mass_share']:.0%} (its interval carries it). To measure the gains, record the same kind of "
            "motion with a known mass at the flange and pass `--known-load MASS BAG` (docs/walkthrough.md)."]
    cells = ", ".join(gain_cells(gains, joint_names))
    com = load.get("com")
    where = ("" if com is None else
             f"; its centre of mass {'as given' if load.get('com_given') else 'as the data read it'}: "
             f"({', '.join(f'{c:.3f}' for c in com)})"
             + ("" if load.get("com_given") else " ± (" + ", ".join(f"{c:.3f}" for c in load["com_ci95"]) + ")")
             + " m in the flange frame")
    return lines + [
        f"Measured against a known load of {load['mass_kg']:g} kg ({load['source']}){where}. Gain per joint with its "
        f"95 % half-width (a joint whose interval the data do not narrow below the prior ±{bound:.0%} is not "
        f"identified by this recording): {cells}.", "",
        f"A payload's mass read with this model carries these intervals (at most ±{gains['mass_share']:.1%} of it)."]


def _priors_table(priors: dict) -> list[str]:
    """The priors in force (``diagnosis_result.priors_in_force``): one row per effect, its bound per joint and its
    source."""
    lines = [f"## Priors ({priors['torque_measurement']})", "",
             "Every effect is bounded by a plausible range from the URDF and how τ_m is measured (docs/method.md "
             "§8.6); an effect at its bound is dropped, and a warning says when the data want it beyond. Bounds per "
             "joint (link_inertia: mass per link; payload: its mass). The flange link "
             f"({priors['flange_mass']:.3f} kg in the URDF) and the other links stay physically consistent.", "",
             "| effect | bound | unit | source |", "|---|---|---|---|"]
    for name, entry in priors.get("effects", {}).items():
        values = ", ".join("open" if v is None else f"{v:.3g}" for v in entry["bound"])
        if name == "drive_gain":
            values = f"{entry['bound'][0]:.3g} on every joint"
        elif name == "joint_offset":
            values = f"{priors['max_joint_offset_deg']:.1f}° on every joint"
        unit = "°" if name == "joint_offset" else entry["unit"]
        lines.append(f"| {name} | {values} | {unit} | {entry['source']} |")
    return lines


def augmentation(diag: Diagnosis, robot: RobotModel, robot_name: str = "") -> dict:
    """The accepted effects as a plain mapping (``augmentation.yaml``); diagnosed against an augmented ``robot``, the
    base augmentation's effects come first and the new ones add to them (``core.estimation.augmentation``), so the file
    is the whole correction relative to the URDF."""
    entries = []
    if robot.augmentation is not None:
        entries += list((yaml.safe_load(robot.augmentation.text) or {}).get("effects") or [])
    for term, th, eff in zip(diag.terms, diag.theta, diag.result["effects"]):
        entries.append({"name": term.name, "joint_indices": [int(j) for j in term.joints],
                        "joints": [robot.joint_names[j] for j in term.joints],
                        "variant": {k: float(v) for k, v in term.variant.items()},
                        "parameters": eff["parameters"], "theta": [float(v) for v in term.full_theta(th)]})
    against = {} if robot.augmentation is None else {"against": robot.augmentation.source}
    return {"robot": robot_name, "joint_names": list(robot.joint_names), **against,
            "convention": "tau_m - tau_EL = sum over effects of design(q, qd, qdd, tau_m) @ theta "
                          "(kvark_ros.gap.effects.augmentation_gap)",
            "drive_gains": diag.result["drive_gains"], "effects": entries}


def write_outputs(diag: Diagnosis, robot: RobotModel, out: Path, robot_name: str = "",
                  plots: bool = True) -> list[Path]:
    """diagnosis.json, augmentation.yaml, report.md and (``plots``) the plots into ``out``, relative to ``robot`` (or
    to ``diag.relative_to``); the paths written."""
    robot = diag.relative_to or robot
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "diagnosis.json", out / "augmentation.yaml", out / "report.md"]
    write_text_atomically(paths[0], json.dumps(diag.result, indent=2))
    write_text_atomically(paths[1], yaml.safe_dump(augmentation(diag, robot, robot_name), sort_keys=False))
    write_text_atomically(paths[2], report(diag, robot))
    if plots:
        from kvark_ros.gap.diagnosis_plots import plot_diagnosis   # matplotlib only when plotting
        paths.extend(plot_diagnosis(diag, robot, out))
    return paths
