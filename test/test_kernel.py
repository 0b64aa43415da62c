"""The compiled K-VARK step (``filter.kernel: numba``) against the numpy reference on the committed bags.

The kernel does the reference's arithmetic in the same order: with the residual model evaluated in Python
(any predictor but a q̇-only KMP) the two agree bit for bit; with the KMP inside the kernel they differ by the
rounding of exp and of the kernel-vector products (measured: |Δτ̂| ≤ 3e-15 max|τ̂|, P 2e-15 relative).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.config import load_config
from kvark_ros.core.estimator import Estimator
from kvark_ros.core.model_store import load_model
from kvark_ros.core.observers import ObserverError, make_observer
from kvark_ros.core.observers.kvark_kernel import KVARKKernelFilter
from kvark_ros.core.observers.kvark_momentum import KVARKMomentumFilter
from kvark_ros.io.alignment import read_inputs

ROOT = Path(__file__).resolve().parents[1]
BAGS = ("panda_contact", "panda_collision")
RELATIVE = 1e-10          # on τ̂ (to its largest magnitude over the bag) and on P (to its largest entry)
SPLIT = 1424              # inside the collision's onset alarms (test_state_transfer.COLLISION_SPLITS)


@pytest.fixture(scope="module")
def config():
    return replace(load_config(ROOT / "config" / "panda.yaml"), model_dir=str(ROOT / "models" / "panda"))


@pytest.fixture(scope="module")
def numba_config(config):
    return replace(config, filter=replace(config.filter, kernel="numba"))


@pytest.fixture(scope="module")
def trained(config):
    return load_model(config.model_dir, config.joint_names)


@pytest.fixture(scope="module")
def inputs(config):
    return {bag: read_inputs(ROOT / "bags" / bag, config)[1] for bag in BAGS}


def _run(estimator: Estimator, inputs, start: int = 0, stop: int | None = None) -> list:
    """Estimates (None while warming up) of samples start..stop."""
    rows = range(start, len(inputs.stamp) if stop is None else stop)
    return [estimator.step(inputs.stamp[k], inputs.q[k], inputs.qd[k], inputs.tau_m[k]) for k in rows]


def _differences(reference: list, kernel: list) -> tuple[float, float, int]:
    """max|Δτ̂| / max|τ̂|, max|ΔP| / max|P| and the number of differing contact or collision flags."""
    assert [e is None for e in reference] == [e is None for e in kernel]
    pairs = [(a, b) for a, b in zip(reference, kernel) if a is not None]
    tau = np.array([a.tau_ext for a, _ in pairs]), np.array([b.tau_ext for _, b in pairs])
    cov = np.array([a.tau_cov for a, _ in pairs]), np.array([b.tau_cov for _, b in pairs])
    flags = sum((a.contact != b.contact) + (a.collision != b.collision) for a, b in pairs)
    return (float(np.abs(tau[0] - tau[1]).max() / np.abs(tau[0]).max()),
            float(np.abs(cov[0] - cov[1]).max() / np.abs(cov[0]).max()), int(flags))


def _assert_states_close(reference: dict, kernel: dict, rtol: float) -> None:
    """Equal keys, shapes and (to rtol of each array's largest entry) values, components included."""
    assert set(reference) == set(kernel)
    for name, value in reference.items():
        other = kernel[name]
        if isinstance(value, dict):
            _assert_states_close(value, other, rtol)
        elif isinstance(value, tuple):
            for a, b in zip(value, other):
                assert np.allclose(a, b, rtol=0.0, atol=rtol * np.abs(a).max()), name
        elif isinstance(value, np.ndarray):
            assert value.shape == other.shape and np.allclose(value, other, rtol=0.0, atol=rtol * np.abs(value).max())
        else:
            assert value == other, name


@pytest.mark.parametrize("bag", BAGS)
def test_kernel_matches_the_numpy_reference_on_the_bags(config, numba_config, trained, inputs, bag):
    """Default kvark (window VB, onset detector, KMP inside the kernel): τ̂, P and the flags of every sample,
    the onset alarms and the final filter state."""
    reference = Estimator.from_config(config, trained, "kvark")
    kernel = Estimator.from_config(numba_config, trained, "kvark")
    assert type(reference.observer) is KVARKMomentumFilter and type(kernel.observer) is KVARKKernelFilter
    tau, cov, flags = _differences(_run(reference, inputs[bag]), _run(kernel, inputs[bag]))
    assert tau <= RELATIVE and cov <= RELATIVE and flags == 0
    assert kernel.observer.onset.alarms == reference.observer.onset.alarms > 0
    _assert_states_close(reference.observer.state(), kernel.observer.state(), RELATIVE)


@pytest.mark.parametrize("name", ["gmr_gp", "kmp_kf_nis", "kf"])
def test_kernel_matches_the_reference_for_other_residuals_and_ablations(config, numba_config, trained, inputs,
                                                                      name):
    """gmr_gp (a GP residual, evaluated in Python and passed in): bit for bit; the ablations kmp_kf_nis (EWMA,
    NIS-scaled Σ_d) and kf (static residual variance) with the KMP inside: to rounding."""
    reference = Estimator.from_config(config, trained, name)
    kernel = Estimator.from_config(numba_config, trained, name)
    tau, cov, flags = _differences(_run(reference, inputs["panda_collision"]),
                                   _run(kernel, inputs["panda_collision"]))
    assert flags == 0 and tau <= RELATIVE and cov <= RELATIVE
    if name == "gmr_gp":
        assert tau == 0.0 and cov == 0.0


def test_kernel_state_transfer_continues_bit_for_bit(numba_config, trained, inputs):
    """continue_from between two kernel estimators, inside the collision's onset alarms, changes no output."""
    data = inputs["panda_collision"]
    whole = _run(Estimator.from_config(numba_config, trained, "kvark"), data)
    old = Estimator.from_config(numba_config, trained, "kvark")
    _run(old, data, 0, SPLIT)
    new = Estimator.from_config(numba_config, trained, "kvark")
    new.continue_from(old)
    for a, b in zip(whole[SPLIT:], _run(new, data, SPLIT)):
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.tau_ext, b.tau_ext) and np.array_equal(a.tau_cov, b.tau_cov)
            assert (a.contact, a.collision) == (b.contact, b.collision)
    assert new.observer.onset.alarms > 0


def test_kernel_applies_runtime_keys(config, numba_config, trained, inputs):
    """A run-time key changed mid-run (filter.ewma_time) reaches the kernel as it reaches the reference."""
    data = inputs["panda_contact"]
    reference = Estimator.from_config(config, trained, "kvark")
    kernel = Estimator.from_config(numba_config, trained, "kvark")
    first = _differences(_run(reference, data, 0, 1000), _run(kernel, data, 0, 1000))
    for estimator in (reference, kernel):
        estimator.observer.configure(replace(estimator.observer.settings, ewma_time=0.05))
    second = _differences(_run(reference, data, 1000), _run(kernel, data, 1000))
    assert max(first[:2] + second[:2]) <= RELATIVE and first[2] == second[2] == 0
    assert kernel.observer.ewma_rate == reference.observer.ewma_rate == pytest.approx(0.002 / 0.05)


@pytest.mark.parametrize("change, named", [({"measurement": "difference"}, "filter.measurement"),
                                           ({"vb_variant": "smoothed"}, "filter.vb_variant")])
def test_kernel_refuses_what_it_does_not_cover(numba_config, trained, change, named):
    """The difference form and the paper/smoothed VB readings stay numpy-only: ObserverError naming the key."""
    settings = replace(numba_config.filter, **change)
    with pytest.raises(ObserverError, match=named):
        make_observer("kvark", trained, settings)
    assert type(make_observer("momentum", trained, settings)).__name__ == "MomentumObserver"   # not a K-VARK filter
