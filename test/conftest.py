"""Shared fixtures: the Panda's nominal model and config, and a small trained model."""
from __future__ import annotations

import fcntl
import importlib
import os
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.robot_model import RobotModel

ROOT = Path(__file__).resolve().parents[1]
STAND_IN = Path(__file__).resolve().parent / "ros_stand_in"
STAND_IN_MODULES = {"rclpy", "rcl_interfaces", "builtin_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs",
                    "std_srvs", "diagnostic_msgs", "ros_stand_in_core"}
NODE_MODULE = "kvark_ros.ros.estimator_node"

# The modules that take longest (seconds of test time on 2 cores, measured with --durations), run first: `make test`
# hands whole modules to its workers in collection order (--dist loadfile), and a long module handed out last keeps
# one worker busy after the other has finished. The rest keep their order.
LONG_MODULES = ("test/gap/test_diagnosis.py", "test/tools/test_train_and_replay.py",
                "test/gap/test_diagnosis_workflow.py", "test/core/test_training_fast_paths.py",
                "test/tools/test_fuzz_corrupt_logs.py", "test/ros/test_node_logic_stand_in.py",
                "test/tools/test_real_benchmark.py", "test/core/test_kvark_filter.py",
                "test/ros/test_node_under_rclpy.py", "test/ros/test_driver_recipes_under_rclpy.py",
                "test/core/test_compiled_step_matches_reference.py", "test/tools/test_walkthrough.py",
                "test/tools/test_evaluate_on_dask.py")


def pytest_ignore_collect(collection_path: Path, config) -> bool | None:
    """With ``-m realtime`` alone (``make test``'s second run), a test module that never uses the mark
    (``pytest.mark.realtime``) is not imported: importing every module to select two of them took ~5 s of that run."""
    if config.getoption("markexpr") == "realtime" and collection_path.suffix == ".py" \
            and collection_path.name.startswith("test_"):
        if "mark.realtime" not in collection_path.read_text(encoding="utf-8"):
            return True
    return None


def pytest_collection_modifyitems(session, config, items):
    """The ``LONG_MODULES`` first, longest first (a stable sort: every module's tests keep their order)."""
    rank = {ROOT / name: k for k, name in enumerate(LONG_MODULES)}
    items.sort(key=lambda item: rank.get(item.path, len(rank)))


# One BLAS/OpenMP thread for the whole session (also exported by the Makefile): a sum split over
# another number of threads rounds differently, and the simulated fixtures must not depend on the
# machine's core count.
threadpool_limits(limits=1)


@pytest.fixture(scope="session")
def panda_config():
    return load_config(ROOT / "config" / "panda.yaml")


@pytest.fixture(scope="session")
def panda(panda_config) -> RobotModel:
    c = panda_config
    return RobotModel(c.urdf, c.joint_names, c.ee_frame, c.flange_frame)


@pytest.fixture(scope="session")
def panda_trained(panda):
    """Residual model and filter tuning from a synthetic free-motion stream (Gaz friction), without the learned
    baselines: no test of this model uses them, and their fits (sparse GP, MLP) were 19 of the 23 s it took. The
    KMP, the tunings, the momentum noise and the interval factors are the same bit for bit either way (the baselines
    are fitted after them from their own seeds). A model with baselines: the committed ``models/panda``
    (``panda_committed``)."""
    from kvark_ros.tools.synthetic import train_synthetic
    return train_synthetic(panda, "panda", seed=3, duration=20.0, baselines=False)


@pytest.fixture(scope="session")
def panda_committed(panda_config):
    """The committed trained model ``models/panda`` (``make model``: the committed bags, with the baselines)."""
    from kvark_ros.core.estimation.model_store import load_model
    return load_model(ROOT / "models" / "panda", panda_config.joint_names)


def shared_directory(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """A directory ``build(path)`` writes once per test session, shared by every xdist worker (pytest-xdist's
    recipe: the workers' base temporary directories have one parent per session; a lock file makes one worker build
    while the others wait for it). For fixtures several test files need the same expensive thing of, e.g. a model
    directory: trained once instead of once per file."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    target = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not target.is_dir():
                staging = root / f"shared-{name}.staging"
                shutil.rmtree(staging, ignore_errors=True)
                build(staging)
                staging.rename(target)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return target


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="module")
def ros():
    """The ROS node module imported against the suite's rclpy stand-in (``test/ros_stand_in``).

    The stand-in is on ``sys.path`` only while a test module uses this fixture; ``kvark_ros.ros`` (the
    node and its helpers, bound to the stand-in's classes) and the stand-in's packages are removed from
    ``sys.modules`` afterwards, so nothing leaks into the next module's fresh import.
    """
    def ours(name: str) -> bool:
        return name.split(".")[0] in STAND_IN_MODULES or name == "kvark_ros.ros" or name.startswith("kvark_ros.ros.")

    saved = {name: module for name, module in sys.modules.items() if ours(name)}
    for name in saved:
        del sys.modules[name]
    sys.path.insert(0, str(STAND_IN))
    try:
        importlib.invalidate_caches()
        node_module = importlib.import_module(NODE_MODULE)
        rclpy = importlib.import_module("rclpy")
        assert rclpy.STAND_IN, "the stand-in, not a real rclpy, must be under test here"
        yield SimpleNamespace(
            node=node_module, rclpy=rclpy, core=importlib.import_module("ros_stand_in_core"),
            parameters=importlib.import_module("kvark_ros.ros.parameters"),
            Parameter=importlib.import_module("rclpy.parameter").Parameter,
            builtin=importlib.import_module("builtin_interfaces.msg"), std=importlib.import_module("std_msgs.msg"),
            sensor=importlib.import_module("sensor_msgs.msg"), diag=importlib.import_module("diagnostic_msgs.msg"),
            exceptions=importlib.import_module("rclpy.exceptions"))
    finally:
        sys.path.remove(str(STAND_IN))
        for name in [name for name in sys.modules if ours(name)]:
            del sys.modules[name]
        sys.modules.update(saved)


def debounced_margin(stamps: np.ndarray, statistics: np.ndarray, threshold: float, debounce: float) -> float:
    """Smallest ratio of the contact threshold to the statistic the debounced flag acts on.

    The flag rises only when ``d²`` stays above the threshold for ``debounce`` s, so what must stay
    below the threshold is, at each sample t, the smallest ``d²`` over [t, t + debounce]. A ratio
    above 1 means no false flag; how far above says how much room a machine or a release has.
    """
    ends = np.searchsorted(stamps, stamps + debounce, side="right")
    held = np.array([statistics[k:end].min() for k, end in enumerate(ends)])
    return float(threshold / held.max())


@pytest.fixture
def saved(monkeypatch) -> list:
    """Every matplotlib Figure saved during the test (still written to its file), for plot tests."""
    from matplotlib.figure import Figure
    figures: list = []
    original = Figure.savefig

    def keep(fig, *args, **kwargs):
        figures.append(fig)
        return original(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures
