"""Contact in the ground truth (core/contact_events.py): touching, contact-free, onsets and spans, one definition
that the metrics, plots and reports share."""
from __future__ import annotations

import numpy as np

from kvark_ros.core.contact_events import CONTACT_TORQUE, SETTLE, contact_free, contact_onsets, contacts, touching
from kvark_ros.tools.metrics import contact_metrics

RATE = 500.0


def _truth(stamp: np.ndarray, spans: list[tuple[float, float, int, float]]) -> np.ndarray:
    """A true τ_ext (T, 3): 0.05 N·m noise (far below CONTACT_TORQUE) plus each (start, end, joint, torque) contact."""
    tau = 0.05 * np.random.default_rng(0).standard_normal((len(stamp), 3))
    for start, end, joint, torque in spans:
        tau[(stamp >= start) & (stamp < end), joint] += torque
    return tau


STAMP = 100.0 + np.arange(int(6 * RATE)) / RATE
# a contact at 1 s that dips below the threshold for 20 ms (one contact, not two), another at 3 s on another joint, a
# third at 4.5 s
TRUTH = _truth(STAMP, [(101.0, 101.5, 0, 2.0), (101.52, 102.0, 0, 2.0), (103.0, 103.5, 2, -1.0),
                       (104.5, 104.8, 1, 1.0)])


def test_contact_onsets_are_the_first_samples_above_the_threshold_after_a_quiet_spell():
    np.testing.assert_allclose(contact_onsets(STAMP, TRUTH), [101.0, 103.0, 104.5])
    np.testing.assert_allclose(contact_onsets(STAMP, TRUTH, limit=2), [101.0, 103.0])
    # touching from the first sample: never seen starting, no onset; NaN truth samples are not contact
    assert len(contact_onsets(STAMP, _truth(STAMP, [(100.0, 102.0, 1, 3.0)]))) == 0
    gappy = TRUTH.copy()
    gappy[: int(0.5 * RATE)] = np.nan
    np.testing.assert_allclose(contact_onsets(STAMP, gappy), [101.0, 103.0, 104.5])


def test_a_contact_spans_its_dips_and_ends_after_its_last_touching_sample():
    """The first contact runs from 101.0 s through its 20 ms dip to its last touching sample at 102.0 s − 1/RATE; the
    samples more than SETTLE after each contact are contact-free, those within it are not (nor is the dip)."""
    touch = touching(TRUTH)
    spans = contacts(STAMP, touch)
    assert [(STAMP[a], STAMP[b - 1]) for a, b in spans] == [(101.0, 102.0 - 1 / RATE), (103.0, 103.5 - 1 / RATE),
                                                             (104.5, 104.8 - 1 / RATE)]
    assert contacts(STAMP, touch, limit=1) == spans[:1]
    free = contact_free(STAMP, touch)
    for a, b in spans:
        end = STAMP[b - 1]
        assert not free[a:b].any()                                              # the dip is not contact-free
        # (one sample of margin each side: the stamps 100 + k/RATE carry ~1e-14 s of rounding)
        assert not free[(STAMP > end) & (STAMP < end + SETTLE - 1 / RATE)].any()
        assert free[np.flatnonzero(STAMP > end + SETTLE + 1 / RATE)[0]]
    assert touching(np.array([[CONTACT_TORQUE, 0.0], [-1.0001 * CONTACT_TORQUE, 0.0]])).tolist() == [False, True]


def test_the_metrics_count_the_contacts_the_plots_draw():
    """A flag raised 10 ms into every contact: three onsets detected (the dip is not a fourth), each 10 ms late."""
    flag = np.zeros(len(STAMP), dtype=bool)
    for a, b in contacts(STAMP, touching(TRUTH)):
        flag[a + 5:b] = True
    figures = contact_metrics(STAMP, flag, np.ones(len(STAMP), dtype=bool), TRUTH)
    assert figures["onsets"] == len(contact_onsets(STAMP, TRUTH)) == 3 and figures["missed_onsets"] == 0
    np.testing.assert_allclose(figures["detection_delay"], [0.01, 0.01, 0.01])
    assert figures["false_contact_share"] == 0.0
