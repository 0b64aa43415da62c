"""The acceptance limits the benchmark reports check, in one place: issues 14 and 17 for the simulated plants
(``tools.benchmark``), restated by issue 28 for the population (``tools.population``)."""
from __future__ import annotations

RMSE_LIMIT = 0.8                  # K-VARK's joint RMSE ≤ 0.8 × momentum's and kf's
ORACLE_LIMIT = 1.3                # and ≤ 1.3 × the oracle's
COVERAGE_RANGE = (0.90, 0.98)     # K-VARK's coverage95, pooled (and per joint on the simulated plants)
