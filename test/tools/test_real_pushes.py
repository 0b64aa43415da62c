"""Known pushes superposed on a contact-free recording (kvark benchmark --real --pushes)."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.cli import main
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.tools.real_benchmark import evaluate
from kvark_ros.tools.real_pushes import DIRECTIONS, FIRST, HOLD, PERIOD, RAMP, SETTLE, push_profile, pushed
from kvark_ros.tools.synthetic import synthetic_stream

RATE = 500.0


def test_each_push_is_a_trapezoid_along_the_next_axis_and_ends_before_the_data():
    time = np.arange(int(7.0 * RATE)) / RATE      # 7 s: pushes at 0.5 and 3.5 s (one at 6.5 s would not end in time)
    profile, starts = push_profile(time, 40.0)
    assert starts == pytest.approx([FIRST, FIRST + PERIOD])
    for index, start in enumerate(starts):
        along = profile @ DIRECTIONS[index]
        at = np.searchsorted(time, [start, start + RAMP / 2, start + RAMP + HOLD / 2, start + 2 * RAMP + HOLD])
        assert along[at] == pytest.approx([0.0, 20.0, 40.0, 0.0], abs=40.0 / (RAMP * RATE))   # one sample's step
    assert not profile[time < FIRST].any() and not profile[time > starts[-1] + 2 * RAMP + HOLD].any()
    assert np.abs(profile).max() == pytest.approx(40.0)


@pytest.mark.parametrize("force", [0.0, -5.0, float("nan")])
def test_a_push_force_that_is_not_a_positive_number_is_refused(force):
    with pytest.raises(ValueError, match="positive number of newtons"):
        push_profile(np.arange(3000) / RATE, force)


def test_a_held_out_part_too_short_for_one_push_is_refused():
    needed = FIRST + 2 * RAMP + HOLD + SETTLE
    with pytest.raises(ValueError, match=f"a push needs {needed:.1f} s"):
        push_profile(np.arange(int((needed - 0.1) * RATE)) / RATE, 40.0)


def test_the_push_enters_the_measured_torque_as_minus_j_transpose_f(panda):
    stream = synthetic_stream(panda, 2.5, rate=RATE, seed=2)
    inputs = EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0)
    pushes = pushed(panda, "base", inputs, 30.0)
    k = int((FIRST + RAMP + HOLD / 2) * RATE)                   # mid-hold: the whole first push, along +x
    assert pushes.truth.wrench[k] == pytest.approx([30.0, 0, 0, 0, 0, 0])
    expected = panda.jacobian(stream.q[k], "base")[:3].T @ np.array([30.0, 0.0, 0.0])
    assert pushes.truth.tau_ext[k] == pytest.approx(expected)
    assert pushes.inputs.tau_m[k] == pytest.approx(stream.tau_m[k] - expected)      # M q̈ + … = τ_m + τ_ext
    assert np.array_equal(pushes.inputs.q, stream.q) and np.array_equal(pushes.inputs.qd, stream.qd)
    assert not (pushes.active & pushes.after).any() and pushes.after.any()


def test_the_observers_follow_the_superposed_pushes_and_let_go(panda, panda_config, panda_trained):
    """Two 20 N pushes on a synthetic stream whose friction the model learned: both filters follow the push (a sign
    error in the superposition would leave an error twice the push) and return to the free-motion level after it."""
    stream = synthetic_stream(panda, 5.5, rate=RATE, seed=9)
    inputs = EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0)
    pushes = pushed(panda, "base", inputs, 20.0)
    results = evaluate(panda_config, panda_trained, inputs, ["kvark", "kf"], lambda _line: None, pushes)
    push_rms = float(np.sqrt(np.mean(pushes.truth.tau_ext[pushes.active] ** 2, axis=0)).mean())
    for name, entry in results.items():
        # During the pushes the error is the ramps' lag; a fifth of the push's own size leaves a factor of ten to a
        # sign error (error ≈ 2 × push). After them what is left is the free-motion error of a learned friction.
        assert entry["push_rmse"]["during"] < 0.2 * push_rms, name
        assert entry["push_rmse"]["after"] < 0.1 * push_rms, name
        assert entry["contact"]["onsets"] == 2 and entry["contact"]["missed_onsets"] == 0, name


def test_pushes_need_a_real_recording(tmp_path, capsys):
    code = main(["benchmark", "--pushes", "40", "--out", str(tmp_path / "out")])
    assert code == 1 and "it needs --real BAG" in capsys.readouterr().err
