"""The contact-onset threshold read at training (core/learning/training.py, docs/method.md §4.7): the least of the
configured one × 2^i at which the contact-free training recordings raise no onset, kept by the model and in force
in every filter built from it."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import load_model, save_model
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.core.estimation.observers.kvark_family import onset_threshold_in_force
from kvark_ros.core.estimation.residual.files import ResidualModelError
from kvark_ros.core.learning.interval_factors import FactorReading
from kvark_ros.core.learning.training import ONSET_RAISES, calibrate_intervals, quiet_onset_threshold, training_data
from kvark_ros.tools.synthetic import synthetic_stream


def _reads(onsets_below: float):
    """A ``read`` that accepts 3 onsets in-sample and 1 on the unseen ends below ``onsets_below``, none from it on,
    and records the thresholds it was asked for."""
    asked = []

    def read(threshold: float):
        asked.append(threshold)
        noisy = 0.0 < threshold < onsets_below
        return FactorReading(np.full(2, threshold), 3 * noisy), FactorReading(np.full(2, threshold), 1 * noisy)
    return read, asked


def test_the_threshold_doubles_until_no_onset_and_the_readings_are_those_at_it():
    read, asked = _reads(onsets_below=200.0)
    threshold, (in_sample, unseen) = quiet_onset_threshold(60.0, read, 34.0, lambda _line: None)
    assert threshold == 240.0 and asked == [60.0, 120.0, 240.0]
    np.testing.assert_array_equal(in_sample.scale, [240.0, 240.0])     # c read on the filter that is kept
    assert unseen.onsets == 0


def test_onsets_on_the_unseen_ends_alone_raise_it_too():
    def read(threshold):
        return FactorReading(np.ones(1), 0), FactorReading(np.ones(1), int(threshold < 100.0))
    assert quiet_onset_threshold(60.0, read, 10.0, lambda _line: None)[0] == 120.0


def test_onsets_at_every_raise_turn_the_detector_off_and_say_so():
    """Onsets still at 8 × the configured threshold (``ONSET_RAISES`` = 3 doublings): the detector cannot tell this
    robot's free motion from a contact, so the model turns it off (0) and c is read with it off."""
    read, asked = _reads(onsets_below=np.inf)
    lines = []
    threshold, (in_sample, _) = quiet_onset_threshold(60.0, read, 34.0, lines.append)
    assert ONSET_RAISES == 3 and asked == [60.0, 120.0, 240.0, 480.0, 0.0] and threshold == 0.0
    assert in_sample.scale[0] == 0.0 and "turned off" in lines[-1] and "4 onsets accepted in 34.0 s" in lines[-1]


def test_a_detector_configured_off_is_read_once_and_stays_off():
    read, asked = _reads(onsets_below=np.inf)
    assert quiet_onset_threshold(0.0, read, 34.0, lambda _line: None)[0] == 0.0 and asked == [0.0]


@pytest.mark.parametrize("configured, trained, in_force", [
    (60.0, 120.0, 120.0),      # the model's, where the training's free motion needed more
    (200.0, 120.0, 200.0),     # the configured one where higher
    (0.0, 120.0, 0.0),         # off in the configuration stays off
    (60.0, 0.0, 0.0),          # off where no threshold up to 8 × kept the training quiet
    (60.0, None, 60.0),        # models trained before it was read
])
def test_the_filter_runs_the_larger_of_the_configured_and_the_models_threshold(panda_config, panda_trained,
                                                                              configured, trained, in_force):
    settings = replace(panda_config.filter, measurement="momentum", onset_threshold=configured)
    model = replace(panda_trained, onset_threshold=trained)
    assert onset_threshold_in_force(settings, model) == in_force
    observer = make_observer("kvark", model, settings)
    assert (observer.onset is None) if in_force == 0.0 else (observer.onset.threshold == in_force)
    observer.configure(replace(settings, ewma_time=0.3))   # the node's run-time change: the configured value stands


def test_training_raises_the_threshold_until_its_contact_free_recordings_raise_no_onset(panda, panda_trained,
                                                                                     panda_config):
    """On a 4 s contact-free synthetic stream the detector accepts onsets at 5, 10 and 20 (253, 17, 2 measured) and
    none at 40: the model keeps 40, and a filter built from it accepts none there. At 60 (the Panda config's) none
    is accepted and the model keeps 60: a robot whose free motion is quiet is not changed."""
    stream = synthetic_stream(panda, 4.0, rate=500.0, seed=7)
    data = training_data(panda, [EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0)])
    settings = replace(panda_config.filter, measurement="momentum")
    lines = []
    raised = calibrate_intervals(panda_trained, data, replace(settings, onset_threshold=5.0), lines.append)
    assert raised.onset_threshold == 40.0
    assert sum("onsets accepted" in line for line in lines) == 3
    quiet = calibrate_intervals(panda_trained, data, replace(settings, onset_threshold=60.0), lines.append)
    assert quiet.onset_threshold == 60.0
    off = calibrate_intervals(panda_trained, data, replace(settings, onset_threshold=0.0), lines.append)
    assert off.onset_threshold is None                  # not read: the detector is off in the configuration
    np.testing.assert_array_equal(raised.interval_scale.scale, off.interval_scale.scale)   # no onset: the same filter


def test_model_round_trip_keeps_the_threshold_and_refuses_a_bad_one(tmp_path, panda_trained):
    save_model(tmp_path / "model", replace(panda_trained, onset_threshold=120.0))
    assert load_model(tmp_path / "model").onset_threshold == 120.0
    save_model(tmp_path / "unread", replace(panda_trained, onset_threshold=None))
    assert load_model(tmp_path / "unread").onset_threshold is None
    for bad in (-1.0, float("nan"), "high"):
        save_model(tmp_path / "bad", replace(panda_trained, onset_threshold=bad))
        with pytest.raises(ResidualModelError, match="onset_threshold"):
            load_model(tmp_path / "bad")
