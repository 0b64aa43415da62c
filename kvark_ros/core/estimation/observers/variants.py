"""K-VARK (paper v1 Algorithm 1) and its ablations A1-A4 (paper v2 Table VI): which covariances adapt.

All five are one disturbance Kalman filter on the momentum virtual measurement with the KMP
mean correction; they differ in which covariances adapt:

=============  =================  ==============  ==============  ================
name           heteroscedastic R  EWMA Σ_emp       NIS-scaled Σ_d  VB-IW Σ_d
=============  =================  ==============  ==============  ================
kf (A1)        –                  –               –               –
kmp_kf (A2)    ✓                  –               –               –
kmp_kf_ewma    ✓                  ✓               –               –
kmp_kf_nis     ✓                  ✓               ✓               –
kvark (A5)     ✓                  ✓               –               ✓
=============  =================  ==============  ==============  ================

The momentum form (``kvark.KVARKFilter``, the default) and the difference form (``kvark_difference``) run every
variant; ``kvark_family`` builds them.
"""
from __future__ import annotations

from dataclasses import dataclass

NIS_SCALE_BOUNDS = (1e-2, 1e4)   # limits of the A4 process-noise scale α, so one outlier cannot freeze or explode Σ_d


@dataclass(frozen=True)
class Variant:
    """Which covariances adapt online."""

    heteroscedastic: bool
    ewma: bool
    nis: bool
    vb: bool


VARIANTS = {
    "kf": Variant(heteroscedastic=False, ewma=False, nis=False, vb=False),
    "kmp_kf": Variant(heteroscedastic=True, ewma=False, nis=False, vb=False),
    "kmp_kf_ewma": Variant(heteroscedastic=True, ewma=True, nis=False, vb=False),
    "kmp_kf_nis": Variant(heteroscedastic=True, ewma=True, nis=True, vb=False),
    "kvark": Variant(heteroscedastic=True, ewma=True, nis=False, vb=True),
}
