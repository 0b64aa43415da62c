"""``kvark benchmark --real``'s interval lines and drive-gain sentence: K-VARK's per-joint coverage of zero and its
interval score against every other observer that reports an interval, judged on the augmented model with the nominal
one beside; the calibration's gains as measured or unidentified. Hand-made results, no training."""
from __future__ import annotations

from kvark_ros.tools.real_benchmark import gains_sentence, interval_lines

NAMES = ("j1", "j2", "j3")


def _entry(per_joint: list[float] | None, score: float | None) -> dict:
    return {"coverage95_per_joint": per_joint, "interval_score95": score, "contact": {}}


def test_kvark_is_judged_per_joint_and_against_the_best_other_interval():
    """Augmented: K-VARK covers 0.90-0.99 per joint (0.90 is at the line: pass) and scores 0.50 N·m against kf 0.55 and
    eso 0.52 (momentum reports no interval: not compared): pass. Nominal, for reference: 0.89 on a joint and 0.60
    against kf's 0.55: not met twice."""
    results = {"augmented": {"kvark": _entry([0.90, 0.95, 0.99], 0.50), "kf": _entry([0.99] * 3, 0.55),
                             "eso": _entry([0.97] * 3, 0.52), "momentum": _entry(None, None)},
               "nominal": {"kvark": _entry([0.89, 0.95, 0.99], 0.60), "kf": _entry([0.99] * 3, 0.55)}}
    assert interval_lines(results)[2:] == [
        "- augmented: K-VARK coverage95 of 0 per joint 0.900-0.990 (≥ 0.9 on every joint: pass)",
        "- augmented: K-VARK interval score 0.500 N·m against the best other observer with an interval, eso 0.520 "
        "(no worse than every other: pass)",
        "- nominal: K-VARK coverage95 of 0 per joint 0.890-0.990 (≥ 0.9 on every joint: not met)",
        "- nominal: K-VARK interval score 0.600 N·m against the best other observer with an interval, kf 0.550 "
        "(no worse than every other: not met)"]
    results["augmented"]["eso"]["interval_score95"] = 0.49
    assert interval_lines(results)[3].endswith("eso 0.490 (no worse than every other: FAIL)")


def test_the_gains_are_stated_as_measured_or_unidentified():
    measured = {"calibrated_with": {"mass_kg": 2.6}, "gain": [1.0, 0.98, 1.026], "ci95": [0.1, 0.012, 0.021],
                "identified": [False, True, True], "torque_measurement": "motor_current", "mass_share": 0.1}
    assert gains_sentence(measured, NAMES) == ("measured with a known load of 2.6 kg: j1 not identified (±0.10 prior), "
                                              "j2 0.980 ± 0.012, j3 1.026 ± 0.021 (95 %)")
    unidentified = {**measured, "calibrated_with": None}
    assert gains_sentence(unidentified, NAMES).startswith("unidentified (τ_m is motor_current; free motion cannot")
    assert "±10%" in gains_sentence(unidentified, NAMES)
