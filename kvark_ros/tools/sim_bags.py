"""The simulated data of ``kvark benchmark``: how much (``BenchmarkPlan``), when the training recordings start
(``training_clocks``), the bags themselves (``simulate_bags``; a motor-current robot's known-load calibration
recording, ``simulate_known_load``) and their reuse on a forced rerun (``reuse_bags``).
Shared by the single-robot benchmark (``tools.benchmark``) and the population (``tools.population_benchmark``).
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from kvark_ros.io import write_run

TEST_SCENARIOS = ("payload", "contact", "collision")
AUGMENTED_OBSERVERS = ("kvark", "kf", "momentum")
KNOWN_LOAD_LABEL = "calibration_known_load"
KNOWN_LOAD_SEED = 50           # its noise and clock seed: the robot's seed + this (training: + 11…, tests: + 100…)


@dataclass(frozen=True)
class BenchmarkPlan:
    """How much data: training recordings and the length of each test recording, s."""

    train_seeds: tuple[int, ...]
    train_duration: float
    test_duration: float


FULL = BenchmarkPlan(train_seeds=(11, 12, 13, 14, 15), train_duration=20.0, test_duration=20.0)
QUICK = BenchmarkPlan(train_seeds=(11, 12), train_duration=10.0, test_duration=8.0)


def training_clocks(count: int) -> list[float]:
    """Plant clocks (s since power-on) of ``count`` training recordings: the middles of ``count`` equal parts of
    the simulator's session. Drawn at random, the five of the full plan all met the torque-offset drifts near
    the same phase (sin > 0.68), and the tests met the opposite one: a training set no user would record."""
    from kvark_ros.sim.scenarios import SESSION_S
    return [SESSION_S * (i + 0.5) / count for i in range(count)]


def simulate_bags(robot: str, plan: BenchmarkPlan, folder: Path, seed: int, log,
                  plant: Path | Mapping[str, Any] | None = None,
                  scenario_plants: Mapping[str, Path | Mapping[str, Any]] | None = None) -> tuple[list[Path], dict]:
    """Training and test bags under ``folder`` (those already there are reused, see ``reuse_bags``); ``plant``: a
    plant file (or mapping) instead of the robot's default; ``scenario_plants``: another plant for some scenarios
    (the population gives its payload scene the plant with the robot's drawn payload).

    The training recordings start evenly spread over the simulator's session after power-on (``training_clocks``),
    as a user records training data from cold to warm; each test recording's start is drawn from its seed.
    """
    from kvark_ros.sim.scenarios import simulate
    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(f"train_excitation_{s}", "excitation", s + seed, plan.train_duration, clock)
            for s, clock in zip(plan.train_seeds, training_clocks(len(plan.train_seeds)))]
    jobs += [(f"test_{name}", name, seed + 100 + i, plan.test_duration, None) for i, name in enumerate(TEST_SCENARIOS)]
    paths: dict[str, Path] = {}
    for step, (label, scenario, scenario_seed, duration, clock) in enumerate(jobs, start=1):
        path = folder / label
        if not path.exists():
            started = time.perf_counter()
            scenario_plant = (scenario_plants or {}).get(scenario, plant)
            write_run(path, simulate(robot, scenario, scenario_seed, duration, scenario_plant, start_time=clock))
            log(f"[benchmark] simulated {step}/{len(jobs)} {label} ({duration:g} s) in "
                f"{time.perf_counter() - started:.1f} s")
        paths[label] = path
    train = [paths[label] for label, scenario, *_ in jobs if scenario == "excitation"]
    tests = {scenario: paths[f"test_{scenario}"] for scenario in TEST_SCENARIOS}
    return train, tests


def simulate_known_load(robot: str, plan: BenchmarkPlan, folder: Path, seed: int, log,
                        plant: Mapping[str, Any]) -> Path:
    """The known-load calibration recording under ``folder`` (reused if there): the first training recording's motion
    again (its seed, its duration), started right after it on the plant clock, carrying the known load (``plant``:
    the robot's plant with it as its payload), with its own noise: how a drive-gain calibration is recorded, the same
    trajectory with and without a weighed mass (Mamedov et al. 2020), so the two differ by the load alone."""
    from kvark_ros.sim.scenarios import simulate
    path = folder / KNOWN_LOAD_LABEL
    if not path.exists():
        started = time.perf_counter()
        folder.mkdir(parents=True, exist_ok=True)
        clock = training_clocks(len(plan.train_seeds))[0] + plan.train_duration
        write_run(path, simulate(robot, "excitation", seed + KNOWN_LOAD_SEED, plan.train_duration, plant,
                                 start_time=clock, motion_seed=seed + plan.train_seeds[0]))
        log(f"[benchmark] simulated {KNOWN_LOAD_LABEL} ({plan.train_duration:g} s, the motion of "
            f"train_excitation_{plan.train_seeds[0]} with the known load) in {time.perf_counter() - started:.1f} s")
    return path


def reuse_bags(old: Path, new: Path) -> None:
    """The bags of the output a ``--force`` run replaces, hard-linked into the new one (copied where a link fails),
    so only what is missing is simulated; the old output stays whole until the swap."""
    def link_or_copy(source: str, target: str) -> None:
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)

    if old.is_dir() and not old.is_symlink():
        shutil.copytree(old, new, copy_function=link_or_copy, dirs_exist_ok=True)
