"""Measure the figures of docs/ by running the commands that produce them, and write them into the documents.

Each section runs one command, keeps the figures it needs in ``docs/results.json`` (with the command, the date,
the wall time, the machine's cores and load), and is written into its ``<!-- generated: NAME -->`` section of a
document together with that command and date; README's results-at-a-glance table is read off the same file. No
figure in docs/ is copied by hand.

    python scripts/results_doc.py                      # every section (about 10 min on 2 cores)
    python scripts/results_doc.py --sections real-panda,node
    python scripts/results_doc.py --render             # rewrite the documents from docs/results.json only
    python scripts/results_doc.py --sections population --keep DIR   # and keep its outputs in DIR/population

``make docs`` runs it with the project's .venv on PATH.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from doc_blocks import ROOT, generated_sections, replace_section, scratch_copy, shell_blocks

DATA = ROOT / "docs" / "results.json"
REAL_PANDA = "../shared/real/panda_gaz2019_trajectory1"
PUSHES = "--pushes 40"      # known 40 N pushes superposed on the held-out part (kvark_ros/tools/real_pushes.py)
# The public UR10e of Mamedov et al. 2020, brought in as a user would (scripts/ur10e_dataset.sh: clones, kvark init,
# kvark import); one unloaded run, its documented start-up (2 s) and final rest (6.5 s) dropped.
REAL_UR10E = ("bash scripts/ur10e_dataset.sh {out}/ur10e > /dev/null && kvark benchmark --real "
              "{out}/ur10e/bags/ur-20_02_19_14harm50sec --config {out}/ur10e/config/ur10e.yaml --rate 0 --trim 2 6.5 "
              f"{PUSHES} --out {{out}}/real")
SCENES = ("payload", "contact", "collision")
PICTURE = ROOT / "docs" / "images" / "contact_joint_torques.png"


@dataclass(frozen=True)
class Section:
    """A measured section: the shell command (``{out}``: a fresh output folder), the document it is written
    into, what to keep of the outputs, and how to render the kept figures."""

    command: str
    document: str
    keep: Callable[[Path, str], dict]
    render: Callable[[dict], str]


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def last_json_line(stdout: str) -> dict:
    return json.loads([line for line in stdout.splitlines() if line.startswith("{")][-1])


def number(value: float | None, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def observer_figures(metrics: dict) -> dict:
    """The figures a table shows of one observer's metrics (replay's ``metrics.json`` entry)."""
    per_joint = metrics.get("coverage95_per_joint")
    return {"joint_rmse": metrics.get("joint_rmse_mean"), "force_rmse": metrics.get("force_rmse_mean"),
            "coverage95": metrics.get("coverage95"),
            "coverage95_min_joint": None if per_joint is None else min(per_joint),
            "interval95": None if metrics.get("interval95_per_joint") is None
            else sum(metrics["interval95_per_joint"]) / len(metrics["interval95_per_joint"]),
            "vector_coverage95": metrics.get("vector_coverage95"),
            "any_joint_miss": metrics.get("any_joint_miss_share"),
            "false_contact": (metrics.get("contact") or {}).get("false_contact_share")}


def keep_scenes(metrics_by_scene: dict[str, dict]) -> dict:
    return {scene: {name: observer_figures(figures) for name, figures in metrics["observers"].items()}
            for scene, metrics in metrics_by_scene.items()}


def scene_table(scenes: dict) -> str:
    """Observers × scenes: joint RMSE (N·m) / coverage95 (lowest joint's in brackets)."""
    names = list(next(iter(scenes.values())))
    lines = ["| observer | " + " | ".join(scenes) + " |", "|---|" + "---|" * len(scenes)]
    for name in names:
        cells = []
        for scene in scenes.values():
            figures = scene.get(name)
            if figures is None:
                cells.append("–")
                continue
            cell = number(figures["joint_rmse"])
            if figures["coverage95"] is not None:
                cell += f" / {number(figures['coverage95'], 2)} ({number(figures['coverage95_min_joint'], 2)})"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def keep_demo(out: Path, stdout: str) -> dict:
    """The demo's figures; its contact run's joint-torque plot becomes README's picture."""
    PICTURE.parent.mkdir(exist_ok=True)
    shutil.copyfile(out / "contact" / "joint_torques.png", PICTURE)
    diagnosis = read_json(out / "diagnosis" / "diagnosis.json")
    return {"scenes": keep_scenes({scene: read_json(out / scene / "metrics.json") for scene in SCENES}),
            "effects": [effect["name"] for effect in diagnosis["effects"]],
            "gap": [diagnosis["gap_before"]["joint_rmse_mean"], diagnosis["gap_after"]["joint_rmse_mean"]],
            "node": [line.replace(str(out), "DIR") for line in stdout.splitlines() if line.startswith("[node-check]")]}


def render_demo(data: dict) -> str:
    effects = ", ".join(data["effects"])
    return (f"Diagnosis of the two excitation bags: {effects}; held-out gap {data['gap'][0]:.3f} → "
            f"{data['gap'][1]:.3f} N·m. Joint RMSE (N·m) / coverage95 (the lowest joint's):\n\n"
            + scene_table(data["scenes"]) + "\n\nThe node check it ends with:\n\n```text\n"
            + "\n".join(re.sub(r"/tmp/kvark-[\w-]+", "DIR", line) for line in data["node"]) + "\n```")


def keep_quick(out: Path, stdout: str) -> dict:
    return {"scenes": keep_scenes(read_json(out / "benchmark" / "results.json")["scenarios"])}


def render_quick(data: dict) -> str:
    return "Joint RMSE (N·m) / coverage95 (the lowest joint's):\n\n" + scene_table(data["scenes"])


def render_simulated(robot: str) -> Callable[[dict], str]:
    """The rendering of a robot's realistic-plant benchmark."""
    return lambda data: f"**{robot}**. " + render_quick(data)


def keep_real(out: Path, stdout: str) -> dict:
    results = read_json(out / "real" / "results.json")
    return {"rate_hz": results["rate_hz"], "samples": results["samples"], "effects": results["augmentation"]["effects"],
            "gap": [results["augmentation"]["gap_before"], results["augmentation"]["gap_after"]],
            "nominal": {name: observer_figures(m) for name, m in results["nominal"].items()},
            "augmented": {name: observer_figures(m) for name, m in results["augmented"].items()},
            **({"pushes": push_figures(results["pushes"])} if "pushes" in results else {})}


def push_figures(pushes: dict) -> dict:
    """What the pushes' table shows: the pushes, and per observer τ_ext RMSE (all, during, after), coverage95 and
    the contact flag's median delay."""
    def delay_ms(metrics: dict) -> float | None:
        median = metrics["contact"].get("detection_delay_median")
        return None if median is None else 1000.0 * median

    return {"force_n": pushes["force_n"], "count": pushes["count"], "hold_s": pushes["hold_s"],
            "ramp_s": pushes["ramp_s"],
            "observers": {name: {"joint_rmse": m["joint_rmse_mean"], "during": m["push_rmse"]["during"],
                                 "after": m["push_rmse"]["after"], "coverage95": m.get("coverage95"),
                                 "delay_ms": delay_ms(m),
                                 "unflagged": m["contact"].get("missed_onsets")}
                          for name, m in pushes["observers"].items()}}


def render_pushes(pushes: dict) -> list[str]:
    lines = ["", f"With {pushes['count']} known pushes of {pushes['force_n']:g} N superposed on the held-out part "
             f"(`--pushes`: τ_m less Jᵀ F, {pushes['hold_s']:g} s holds between {pushes['ramp_s']:g} s ramps, q and q̇ "
             "as recorded), augmented model:", "",
             "| observer | τ_ext RMSE (N·m) | during the pushes | after them | coverage95 | contact flag median (ms) "
             "| pushes never flagged |", "|---|---|---|---|---|---|---|"]
    for name, figures in pushes["observers"].items():
        lines.append(f"| {name} | {number(figures['joint_rmse'])} | {number(figures['during'])} | "
                     f"{number(figures['after'])} | {number(figures['coverage95'])} | "
                     f"{number(figures['delay_ms'], 0)} | {figures['unflagged']} |")
    return lines


def render_real(data: dict) -> str:
    lines = [f"Trained and diagnosed on the first {data['samples']['train']} samples, held out "
             f"{data['samples']['held_out']} at about {data['rate_hz']:.0f} Hz with a true τ_ext of zero. Diagnosis: "
             f"{', '.join(data['effects'])}; held-out gap {data['gap'][0]:.2f} → {data['gap'][1]:.2f} N·m. "
             "Nominal model / augmented model:", "",
             "| observer | false τ_ext (N·m) | false force (N) | coverage95 of 0 | mean 1.96 σ (N·m) "
             "| vector coverage95 | any-joint miss | false contact |", "|---|---|---|---|---|---|---|---|"]
    for name, nominal in data["nominal"].items():
        augmented = data["augmented"][name]
        cells = [f"{number(nominal.get(key), digits)} / {number(augmented.get(key), digits)}"
                 if nominal.get(key) is not None else "–"
                 for key, digits in (("joint_rmse", 3), ("force_rmse", 2), ("coverage95", 3), ("interval95", 2),
                                     ("vector_coverage95", 3), ("any_joint_miss", 3), ("false_contact", 3))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines + (render_pushes(data["pushes"]) if "pushes" in data else []))


POPULATION_FIGURES = ("kvark_aug RMSE", "kf_aug RMSE", "momentum_aug RMSE", "oracle RMSE", "kvark_aug coverage95",
                      "kvark_aug coverage95 moving", "kvark_aug coverage95 per joint")


def keep_population(out: Path, stdout: str) -> dict:
    results = read_json(out / "population" / "results.json")
    return {"seed": results["seed"], "robots": [robot["robot"]["label"] for robot in results["robots"]],
            "failed": len(results["failed"]),
            "groups": {name: {"cells": group["cells"], "acceptance": group["acceptance"],
                              "figures": {key: group["distributions"][key] for key in POPULATION_FIGURES
                                          if key in group["distributions"]}}
                       for name, group in results["groups"].items()}}


def render_population(data: dict) -> str:
    failed = f"; {data['failed']} failed" if data["failed"] else ""
    lines = [f"Seed {data['seed']}: {', '.join(data['robots'])}{failed}. "
             "Median / 90th percentile / worst over robots × scenes (for coverage the 10th percentile and the "
             "lowest), on the diagnosed model:", "",
             "| arm class | cells | " + " | ".join(POPULATION_FIGURES) + " |",
             "|---|---|" + "---|" * len(POPULATION_FIGURES)]
    for name, group in data["groups"].items():
        cells = [" / ".join(number(group["figures"][key][q], 3) for q in ("median", "p90", "worst"))
                 if key in group["figures"] else "–" for key in POPULATION_FIGURES]
        lines.append(f"| {name} | {group['cells']} | " + " | ".join(cells) + " |")
    lines += ["", "The acceptance lines (their limits: `kvark_ros/tools/acceptance.py`), pooled over every robot and scene:",
              ""]
    lines += data["groups"]["pooled"]["acceptance"]
    return "\n".join(lines)


NODE_RUNS = ("", "--reload-at 2.5", "--rate 2", "--rate 2 --load-cores 1", "--rate 2 --load-cores 1 --reload-at 2.5")
NODE_FIGURES = ("estimates_matched", "estimates_expected", "max_abs_difference", "node_reported_lost", "latency_ms_p50",
                "latency_ms_p99", "latency_ms_max", "node_cpu_cores", "checker_cpu_cores", "machine_cpu_cores", "cores",
                "input_rate_hz", "load_cores", "reload_at")


def keep_node(out: Path, stdout: str) -> dict:
    """Each run's figures, in the order of ``NODE_RUNS``."""
    return {"runs": [{key: read_json(out / f"node{k}.json")[key] for key in NODE_FIGURES}
                     for k in range(1, len(NODE_RUNS) + 1)]}


def render_node(data: dict) -> str:
    lines = ["| input | estimates equal to replay (max abs Δτ, N·m) | joint states lost "
             "| latency p50 / p99 / max (ms) | node CPU (core) | node-check CPU (core) | machine CPU (cores) |",
             "|---|---|---|---|---|---|---|"]
    for run in data["runs"]:
        label = f"{run['input_rate_hz']:.0f} Hz"
        label += f", {run['load_cores']} core busy" if run["load_cores"] else ""
        label += f", reload at {run['reload_at']:g} s" if run["reload_at"] is not None else ""
        lines.append(f"| {label} | {run['estimates_matched']} of {run['estimates_expected']} "
                     f"({run['max_abs_difference']:.1e}) | {run['node_reported_lost']} | {run['latency_ms_p50']:.2f} / "
                     f"{run['latency_ms_p99']:.2f} / {run['latency_ms_max']:.1f} | {run['node_cpu_cores']:.3f} | "
                     f"{run['checker_cpu_cores']:.3f} | {run['machine_cpu_cores']:.2f} of {run['cores']} |")
    return "\n".join(lines)


def node_costs(record: dict) -> str:
    """README's lines on what the node costs per input rate, from the recorded node section."""
    lines = ["| input | node CPU (core) | latency p99 (ms) | joint states lost |", "|---|---|---|---|"]
    for run, options in zip(record["figures"]["runs"], NODE_RUNS):
        if run["reload_at"] is None:
            label = f"{run['input_rate_hz']:.0f} Hz" + (", the other core busy" if run["load_cores"] else "")
            lines.append(f"| {label} (`{options or '--rate 1'}`) | {run['node_cpu_cores']:.2f} | "
                         f"{run['latency_ms_p99']:.2f} | {run['node_reported_lost']} |")
    return "\n".join(lines) + f"\n\n`kvark node-check --config config/panda.yaml --bag bags/panda_contact` with the " \
        f"options in brackets, {record['date']} ({record['cores']} cores; docs/results.md has every figure)."


def keep_node_instructions(out: Path, stdout: str) -> dict:
    figures = read_json(out / "node.json")
    return {key: figures[key] for key in ("instructions_per_estimate", "idle_instructions_per_s", "estimates_matched",
                                          "estimates_expected", "max_abs_difference")}


def render_node_instructions(data: dict) -> str:
    idle = data["idle_instructions_per_s"] / 1e6
    return (f"{data['instructions_per_estimate'] / 1e3:.0f} k instructions per estimate: the node process, every "
            f"thread (inputs, estimation, publishing, Fast DDS), its idle work ({idle:.2f} M instructions/s) "
            f"subtracted; {data['estimates_matched']} of {data['estimates_expected']} estimates equal to replay "
            f"within {data['max_abs_difference']:.1e} N·m under valgrind.")


def keep_bench(out: Path, stdout: str) -> dict:
    return last_json_line(stdout)["observers"]


def render_bench(data: dict) -> str:
    lines = ["| observer | p50 µs | p99 µs |", "|---|---|---|"]
    lines += [f"| {name} | {figures['p50_us']:.1f} | {figures['p99_us']:.1f} |" for name, figures in data.items()]
    return "\n".join(lines)


def keep_soak(out: Path, stdout: str) -> dict:
    return last_json_line(stdout)


def render_soak(data: dict) -> str:
    return "```json\n" + json.dumps(data) + "\n```"


def keep_walkthrough(out: Path, stdout: str) -> dict:
    folder = out / "walkthrough" / ROOT.name
    diagnosis = read_json(folder / "results" / "myur5_diagnosis" / "diagnosis.json")
    replay = read_json(folder / "results" / "myur5_replay" / "metrics.json")
    return {"effects": [{"name": e["name"], "joints": e["joints"]} for e in diagnosis["effects"]],
            "warnings": diagnosis["warnings"],
            "gap": [diagnosis["gap_before"]["joint_rmse_mean"], diagnosis["gap_after"]["joint_rmse_mean"]],
            "observers": {name: observer_figures(m) for name, m in replay["observers"].items()}}


def render_walkthrough(data: dict) -> str:
    lines = [f"Diagnosis: {', '.join(effect['name'] for effect in data['effects'])}; held-out gap "
             f"{data['gap'][0]:.2f} → {data['gap'][1]:.2f} N·m; warnings: {len(data['warnings']) or 'none'}.", "",
             "Replay of the second log (true τ_ext = 0): false τ_ext (N·m) / coverage95 of zero:", "",
             "| observer | false τ_ext | coverage95 of 0 |", "|---|---|---|"]
    lines += [f"| {name} | {number(f['joint_rmse'])} | {number(f['coverage95'], 2)} |"
              for name, f in data["observers"].items()]
    return "\n".join(lines)


WALKTHROUGH = "docs/walkthrough.md"
SECTIONS = {
    "demo": Section("make demo RESULTS={out}", "docs/results.md", keep_demo, render_demo),
    "simulated-panda": Section("kvark benchmark --robot panda --out {out}/benchmark", "docs/results.md",
                               keep_quick, render_simulated("Panda")),
    "simulated-ur5": Section("kvark benchmark --robot ur5 --out {out}/benchmark", "docs/results.md",
                             keep_quick, render_simulated("UR5")),
    "simulated-quick": Section("kvark benchmark --robot panda --quick --out {out}/benchmark", "docs/results.md",
                               keep_quick, render_quick),
    "real-panda": Section(f"kvark benchmark --real {REAL_PANDA} {PUSHES} --out {{out}}/real", "docs/results.md",
                          keep_real, render_real),
    "real-ur10e": Section(REAL_UR10E, "docs/results.md", keep_real, render_real),
    "population": Section("kvark benchmark --population 6 --seed 29 --out {out}/population", "docs/results.md",
                          keep_population, render_population),
    "node": Section("k=0; for run in " + " ".join(f'"{run}"' for run in NODE_RUNS) + "; do k=$((k+1)); "
                    "kvark node-check --config config/panda.yaml --bag bags/panda_contact $run --json {out}/node$k.json"
                    " || exit 1; done", "docs/results.md", keep_node, render_node),
    "node-instructions": Section("kvark node-check --config config/panda.yaml --bag bags/panda_contact --rate 0.1 "
                                 "--callgrind {out}/callgrind --json {out}/node.json", "docs/results.md",
                                 keep_node_instructions, render_node_instructions),
    "latency": Section("kvark bench --robot panda --observer all", "docs/results.md", keep_bench, render_bench),
    "soak": Section("kvark soak --steps 1000000", "docs/results.md", keep_soak, render_soak),
    "walkthrough": Section("python scripts/results_doc.py --sections walkthrough", WALKTHROUGH,
                           keep_walkthrough, render_walkthrough),
}


def run_walkthrough(out: Path) -> subprocess.CompletedProcess:
    copy = scratch_copy(out / "walkthrough")
    script = "set -euo pipefail\n" + "\n".join(block.text for block in shell_blocks(WALKTHROUGH) if block.kind == "run")
    return subprocess.run(["bash", "-c", script], cwd=copy, text=True, capture_output=True)


def measure(name: str, section: Section, keep: Path | None = None) -> dict:
    """Run ``section``'s command in a fresh folder (``keep / name`` if given, else a temporary one); what it keeps,
    with the command, date, time and load."""
    with tempfile.TemporaryDirectory(prefix=f"kvark-{name}-") as temporary:
        out, load = (Path(temporary) if keep is None else keep / name), os.getloadavg()[0]
        if keep is not None:
            out.mkdir(parents=True)         # a new folder: never mixes with an earlier run's outputs
        started = time.monotonic()
        print(f"[docs] {name}: {section.command}", flush=True)
        if name == "walkthrough":
            result = run_walkthrough(out)
        else:
            result = subprocess.run(section.command.format(out=out), shell=True, cwd=ROOT, text=True,
                                    stdout=subprocess.PIPE, stderr=None)
        if result.returncode != 0:
            sys.stdout.write(result.stdout or "")
            raise SystemExit(f"[docs] {name}: the command failed (exit {result.returncode})")
        seconds = time.monotonic() - started
        figures = section.keep(out, result.stdout)
    return {"command": section.command.replace("{out}/", "DIR/").replace("{out}", "DIR"),
            "date": datetime.date.today().isoformat(), "seconds": round(seconds),
            "cores": os.cpu_count(), "load": round(load, 1), "figures": figures}


def provenance(record: dict) -> str:
    return (f"Produced by `{record['command']}` on {record['date']} in {record['seconds']} s "
            f"({record['cores']} cores, load average {record['load']} at the start).")


def glance_table(records: dict) -> str:
    """README's results at a glance, from the recorded sections."""
    rows = ["| where | kvark | best other observer | kf | what |", "|---|---|---|---|---|"]
    for key, label in (("real-panda", "real Panda"), ("real-ur10e", "real UR10e")):
        if key in records:
            augmented = records[key]["figures"]["augmented"]
            best = min((n for n in augmented if n != "kvark"), key=lambda n: augmented[n]["joint_rmse"])
            rows.append(f"| {label}, held out (docs/results.md) | {augmented['kvark']['joint_rmse']:.3f} | {best} "
                        f"{augmented[best]['joint_rmse']:.3f} | {augmented['kf']['joint_rmse']:.3f} "
                        "| false τ_ext, N·m |")
            pushes = records[key]["figures"].get("pushes")
            if pushes:
                observers = pushes["observers"]
                best = min((n for n in observers if n != "kvark"), key=lambda n: observers[n]["joint_rmse"])
                rows.append(f"| {label}, held out with {pushes['force_n']:g} N pushes superposed | "
                            f"{observers['kvark']['joint_rmse']:.3f} | {best} {observers[best]['joint_rmse']:.3f} | "
                            f"{observers['kf']['joint_rmse']:.3f} | τ_ext RMSE, N·m |")
    population = records.get("population")
    if population:
        for name, group in population["figures"]["groups"].items():
            medians = {key.split()[0].split("_")[0]: group["figures"][key]["median"] for key in
                       ("kvark_aug RMSE", "kf_aug RMSE", "momentum_aug RMSE", "oracle RMSE") if key in group["figures"]}
            best = min((n for n in medians if n not in ("kvark", "oracle")), key=medians.get)
            rows.append(f"| simulated population, seed {population['figures']['seed']}, {name} (median of "
                        f"{group['cells']} cells) | {medians['kvark']:.3f} | {best} {medians[best]:.3f} | "
                        f"{medians['kf']:.3f} | joint RMSE, N·m |")
    for key, label in (("simulated-panda", "simulated Panda, realistic plant"),
                       ("simulated-ur5", "simulated UR5, realistic plant"), ("demo", "simulated Panda, `make demo`")):
        if key in records:
            for scene, observers in records[key]["figures"]["scenes"].items():
                best = min((n for n in observers if n not in ("kvark", "oracle")),
                           key=lambda n: observers[n]["joint_rmse"])
                rows.append(f"| {label}, {scene} | {observers['kvark']['joint_rmse']:.3f} | {best} "
                            f"{observers[best]['joint_rmse']:.3f} | {observers['kf']['joint_rmse']:.3f} "
                            f"| joint RMSE, N·m |")
    dates = sorted({record["date"] for record in records.values()})
    when = dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"
    return "\n".join(rows) + f"\n\nFrom `docs/results.json` (`make docs`, {when})."


def render(records: dict) -> None:
    """Write every recorded section into its document, and README's glance table."""
    documents: dict[str, str] = {}
    for name, record in records.items():
        section = SECTIONS[name]
        text = documents.get(section.document) or (ROOT / section.document).read_text()
        documents[section.document] = replace_section(text, name, provenance(record) + "\n\n"
                                                      + section.render(record["figures"]))
    readme = replace_section((ROOT / "README.md").read_text(), "glance", glance_table(records))
    if "node" in records and "node-costs" in generated_sections(readme):
        readme = replace_section(readme, "node-costs", node_costs(records["node"]))
    documents["README.md"] = readme
    for document, text in documents.items():
        (ROOT / document).write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated: {', '.join(SECTIONS)}")
    parser.add_argument("--render", action="store_true", help="only rewrite the documents from docs/results.json")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="write each section's outputs to DIR/SECTION (a new folder) and keep them")
    args = parser.parse_args(argv)
    records = read_json(DATA) if DATA.exists() else {}
    if not args.render:
        for name in args.sections.split(","):
            if name not in SECTIONS:
                parser.error(f"unknown section {name!r}; choose from {', '.join(SECTIONS)}")
            records[name] = measure(name, SECTIONS[name], args.keep)
            DATA.write_text(json.dumps(records, indent=1, ensure_ascii=False) + "\n")
    render({name: records[name] for name in SECTIONS if name in records})
    return 0


if __name__ == "__main__":
    sys.exit(main())
