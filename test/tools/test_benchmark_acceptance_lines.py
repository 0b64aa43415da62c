"""The simulated benchmark's acceptance lines (tools/benchmark.acceptance): issues 14 and 17's checks say pass or
FAIL with the figures, at the issues' limits."""
from __future__ import annotations

from kvark_ros.tools.benchmark import acceptance


def _scenario(kvark_rmse, coverage, per_joint, vector, contact=None):
    kvark = {"joint_rmse_mean": kvark_rmse, "coverage95": coverage, "coverage95_per_joint": per_joint,
             "vector_coverage95": vector, "contact": contact}
    return {"observers": {"kvark": kvark, "kf": {"joint_rmse_mean": 1.0}, "momentum": {"joint_rmse_mean": 2.0},
                          "oracle": {"joint_rmse_mean": 0.5}}}


def test_every_check_passes_or_fails_at_the_issues_limits():
    lines = acceptance({
        "payload": _scenario(0.65, 0.95, [0.90, 0.98], 0.90),
        "contact": _scenario(0.81, 0.985, [0.899, 0.95], 0.899,
                             {"onsets": 1, "missed_onsets": 0, "detection_delay": [0.024]}),
        "collision": _scenario(0.5, 0.95, [0.95, 0.95], 0.95,
                               {"onsets": 4, "missed_onsets": 1, "detection_delay": [0.03, 0.036, 0.034]}),
    })
    assert "- payload: K-VARK / kf joint RMSE = 0.65 (≤ 0.8: pass)" in lines
    assert "- payload: K-VARK / oracle joint RMSE = 1.30 (≤ 1.3: pass)" in lines           # 0.65 / 0.5: at the limit
    assert "- contact: K-VARK / kf joint RMSE = 0.81 (≤ 0.8: FAIL)" in lines
    assert "- contact: K-VARK / oracle joint RMSE = 1.62 (≤ 1.3: FAIL)" in lines
    assert "- payload: K-VARK coverage95 per joint 0.900-0.980 (0.9-0.98: pass)" in lines   # both ends inside
    assert "- contact: K-VARK coverage95 = 0.985 (0.9-0.98: FAIL)" in lines
    assert "- contact: K-VARK coverage95 per joint 0.899-0.950 (0.9-0.98: FAIL, joints [1])" in lines
    assert "- payload: K-VARK vector coverage95 = 0.900 (0.95 ± 0.05: pass)" in lines
    assert "- contact: K-VARK vector coverage95 = 0.899 (0.95 ± 0.05: FAIL)" in lines
    assert "- contact: K-VARK contact flag: 1 of 1 onsets after 24 ms (pass: none missed)" in lines
    assert "- collision: K-VARK contact flag: 3 of 4 onsets after 30, 36, 34 ms (FAIL: none missed)" in lines
    assert not any(line.startswith("- payload: K-VARK contact flag") for line in lines)     # no onset: no line


def test_a_scenario_without_kvark_or_without_intervals_gives_only_what_it_has():
    lines = acceptance({"payload": {"observers": {"kf": {"joint_rmse_mean": 1.0}}},
                        "contact": _scenario(0.5, None, None, None)})
    assert lines == ["- contact: K-VARK / momentum joint RMSE = 0.25 (≤ 0.8: pass)",
                     "- contact: K-VARK / kf joint RMSE = 0.50 (≤ 0.8: pass)",
                     "- contact: K-VARK / oracle joint RMSE = 1.00 (≤ 1.3: pass)"]


def test_the_interval_score_line_holds_kvark_to_kf():
    """Interval scores (N·m) 1.20 against kf's 1.20 (equal: no worse) pass, 1.25 against 1.20 fail; a scenario where
    kf reports none gives no line."""
    equal, worse = _scenario(0.5, 0.95, [0.95], 0.95), _scenario(0.5, 0.95, [0.95], 0.95)
    for scenario, score in ((equal, 1.20), (worse, 1.25)):
        scenario["observers"]["kvark"]["interval_score95"] = score
        scenario["observers"]["kf"]["interval_score95"] = 1.20
    lines = acceptance({"payload": equal, "contact": worse, "collision": _scenario(0.5, 0.95, [0.95], 0.95)})
    assert "- payload: K-VARK mean interval score (95 %) = 1.200 N·m, kf's 1.200 (no worse: pass)" in lines
    assert "- contact: K-VARK mean interval score (95 %) = 1.250 N·m, kf's 1.200 (no worse: FAIL)" in lines
    assert not any(line.startswith("- collision: K-VARK mean interval score") for line in lines)
