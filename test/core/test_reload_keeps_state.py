"""Model reload without a restart: a rebuilt estimator continues from the old one's state.

The ROS node's ``~/reload_model`` builds a new ``Estimator`` and swaps it in between two samples;
with ``Estimator.continue_from`` reloading the same model must change no output, bit for bit.
"""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.config import OBSERVER_NAMES, load_config
from kvark_ros.core.estimation.estimator import Estimate, Estimator
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.observers.momentum_observers import make_momentum_observer
from kvark_ros.core.estimation.residual import ResidualModelError
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io import read_run
from kvark_ros.io.recorded_inputs import estimator_inputs

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
MODEL = ROOT / "models" / "panda"
BAG = ROOT / "bags" / "panda_collision"
OBSERVERS = [name for name in OBSERVER_NAMES if name != "oracle"]    # oracle needs the simulator's plant
# Samples of the collision in BAG where the default K-VARK's short-memory state matters: the onset
# detector accepts jumps at 1420-1426 (its hypotheses span onset_window_time = 20 ms = 10 samples) and the contact
# flag is pending (debounce running) over 1420-1429 (raise) and 1516-1525 (release).
COLLISION_SPLITS = (1424, 1520)


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


@pytest.fixture(scope="module")
def trained(config):
    """The committed model; it has the learned baselines (gmr_gp, gpadkf, nnadkf)."""
    return load_model(MODEL, config.joint_names)


@pytest.fixture(scope="module")
def inputs(config):
    return estimator_inputs(read_run(BAG, config.joint_names))


def _run(estimator: Estimator, inputs, start: int, stop: int) -> list[Estimate | None]:
    return [estimator.step(inputs.stamp[k], inputs.q[k], inputs.qd[k], inputs.tau_m[k]) for k in range(start, stop)]


def _assert_identical(got: list[Estimate | None], expected: list[Estimate | None]) -> None:
    """Same estimates, bit for bit: τ_ext, P, wrench and its covariance, contact flag."""
    assert len(got) == len(expected)
    for k, (a, b) in enumerate(zip(got, expected)):
        assert (a is None) == (b is None), f"sample {k}"
        if a is None:
            continue
        assert a.stamp == b.stamp and a.contact == b.contact, f"sample {k}"
        for field in ("tau_ext", "tau_cov", "wrench", "wrench_cov"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None), f"sample {k}: {field}"
            assert x is None or np.array_equal(x, y), f"sample {k}: {field}"


def _check_reload(config, trained, inputs, observer: str, half: int | None = None) -> Estimator:
    """Uninterrupted run vs. a run whose estimator is rebuilt (model read anew) at sample ``half``
    (default: halfway); returns the rebuilt one."""
    total = len(inputs.stamp)
    half = total // 2 if half is None else half
    uninterrupted = _run(Estimator.from_config(config, trained, observer), inputs, 0, total)
    old = Estimator.from_config(config, trained, observer)
    _run(old, inputs, 0, half)
    new = Estimator.from_config(config, observer=observer)          # as ~/reload_model: model read from disk
    new.continue_from(old)
    _assert_identical(_run(new, inputs, half, total), uninterrupted[half:])
    # The old estimator is untouched by the transfer (copies, not shared arrays).
    _assert_identical(_run(old, inputs, half, total), uninterrupted[half:])
    assert sum(new.counts.values()) == total - half                 # counts are not carried over
    return new


@pytest.mark.parametrize("observer", OBSERVERS)
def test_reloading_the_same_model_changes_no_output(config, trained, inputs, observer):
    _check_reload(config, trained, inputs, observer)


@pytest.mark.parametrize("split", COLLISION_SPLITS)
def test_reloading_during_a_collision_changes_no_output(config, trained, inputs, split):
    """Rebuilt while the onset detector's hypotheses and the contact debounce are live (COLLISION_SPLITS)."""
    old = Estimator.from_config(config, trained, "kvark")
    _run(old, inputs, 0, split)
    assert old.observer.window is not None and old.observer.onset is not None
    assert old.contact._since is not None                           # a flag change is pending
    new = _check_reload(config, trained, inputs, "kvark", split)
    if split <= 1426:
        assert new.observer.onset.alarms > old.observer.onset.alarms   # jumps accepted after the transfer


def test_difference_form_kvark_continues_exactly(trained, inputs):
    config = load_config(CONFIG, filter__measurement="difference", filter__vb_variant="paper")
    new = _check_reload(config, trained, inputs, "kvark")
    assert type(new.observer).__name__ == "KVARKDifferenceFilter"


def test_another_observer_is_refused(config, trained, inputs):
    old = Estimator.from_config(config, trained, "kvark")
    _run(old, inputs, 0, 10)
    for observer in ("kmp_kf", "kfmo", "gmr_gp"):                  # other name; other class; same class, other name
        new = Estimator.from_config(config, trained, observer)
        with pytest.raises(ValueError, match="cannot continue"):
            new.continue_from(old)
        assert new._stamp is None                                   # nothing copied


def test_other_joints_are_refused(config, trained):
    joints = config.joint_names[:6]
    six = replace(config, joint_names=joints)
    robot = RobotModel(config.urdf, joints, config.ee_frame, config.flange_frame)
    old = Estimator(six, robot, make_momentum_observer("kfmo", 6))
    new = Estimator.from_config(config, trained, "kfmo")
    with pytest.raises(ValueError, match="other joints"):
        new.continue_from(old)


def test_a_state_that_does_not_fit_is_refused_and_changes_nothing(config, trained, inputs):
    """Other onset window: the detector's arrays differ in shape; wrong keys are refused too."""
    old = Estimator.from_config(config, trained, "kvark")
    _run(old, inputs, 0, 100)
    other = load_config(CONFIG, filter__onset_window_time=config.filter.onset_window_time + 0.002)
    new = Estimator.from_config(other, trained, "kvark")
    before = new.observer.state()
    with pytest.raises(ValueError, match="shape"):
        new.continue_from(old)
    assert new._stamp is None and new.observer.state()["onset"]["slot"] == before["onset"]["slot"]
    state = old.observer.state()
    del state["tau"]
    with pytest.raises(ValueError, match="keys"):
        new.observer.load_state(state)


def test_state_is_a_copy(config, trained, inputs):
    """Changing a handed-out or loaded state leaves the observer alone."""
    estimator = Estimator.from_config(config, trained, "kvark")
    _run(estimator, inputs, 0, 50)
    state = estimator.observer.state()
    tau = estimator.observer.tau.copy()
    state["tau"] += 1.0
    assert np.array_equal(estimator.observer.tau, tau)
    estimator.observer.load_state(state)
    state["tau"] += 1.0
    assert np.array_equal(estimator.observer.tau, tau + 1.0)


def test_an_estimator_reads_only_the_residual_its_observer_runs(config, tmp_path):
    """A reload reads the KMP and, for a learned baseline, that baseline alone: the other baselines' files are not
    read (most of a reload's work, done while samples arrive), so a damaged one stops only the observer using it,
    with its file named."""
    shutil.copytree(MODEL, tmp_path / "model")
    (tmp_path / "model" / "mlp.npz").write_bytes(b"not an npz file")
    config = replace(config, model_dir=str(tmp_path / "model"))
    assert dict(Estimator.from_config(config, observer="kvark").trained.baselines) == {}
    assert set(Estimator.from_config(config, observer="gmr_gp").trained.baselines) == {"gmr_gp"}
    with pytest.raises(ResidualModelError, match="mlp.npz"):
        Estimator.from_config(config, observer="nnadkf")
    assert set(load_model(MODEL, config.joint_names).baselines) == {"gmr_gp", "gpadkf", "nnadkf"}
