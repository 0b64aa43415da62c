"""Every observer by name: the one table behind config key ``observer``, CLI ``--observers`` and ``make_observer``.

One line an observer: its name, the module whose ``build(name, trained, settings, oracle)`` makes it, and what it
is. The table is data only (it imports nothing of the package), so the config schema checks a name without loading
an observer, and ``make_observer`` imports only the module of the observer asked for. Adding an observer is its
module plus one line here; the order is the order of ``--observers all`` and of every report.
"""
from __future__ import annotations

from typing import NamedTuple


class ObserverEntry(NamedTuple):
    """An observer: its name, the module that builds it (``build(name, trained, settings, oracle)``), its help."""

    name: str
    module: str
    help: str


_KVARK = "kvark_ros.core.estimation.observers.kvark_family"
_LEARNED = "kvark_ros.core.estimation.observers.learned_baselines"
_MOMENTUM = "kvark_ros.core.estimation.observers.momentum_family"

OBSERVERS = (
    ObserverEntry("kvark", _KVARK, "K-VARK (paper v1 Algorithm 1): KMP residual, adaptive Σ_ν, VB Σ_d"),
    ObserverEntry("kf", _KVARK, "ablation A1 (paper v2 Table VI): the filter without residual or adaptation"),
    ObserverEntry("kmp_kf", _KVARK, "ablation A2: KMP residual in a fixed-noise filter"),
    ObserverEntry("kmp_kf_ewma", _KVARK, "ablation A3: A2 with EWMA empirical measurement noise"),
    ObserverEntry("kmp_kf_nis", _KVARK, "ablation A4: A2 with NIS-scaled process noise"),
    ObserverEntry("gmr_gp", _LEARNED, "GMR reference → GP residual mean/variance in the K-VARK filter"),
    ObserverEntry("gpadkf", _LEARNED, "sparse-GP residual in an adaptive disturbance KF (after Wei et al. 2023)"),
    ObserverEntry("nnadkf", _LEARNED, "MLP residual mean, static covariances (the A1 filter)"),
    ObserverEntry("momentum", _MOMENTUM, "first-order generalized-momentum observer (De Luca & Mattone 2005)"),
    ObserverEntry("kfmo", _MOMENTUM, "Kalman filter momentum observer (Wahrburg et al. 2018)"),
    ObserverEntry("sh_akfmo", _MOMENTUM, "KFMO with Sage-Husa adaptive noise"),
    ObserverEntry("vbkfmo_q", _MOMENTUM, "KFMO with a variational-Bayes predicted covariance (Huang et al. 2018)"),
    ObserverEntry("eso", _MOMENTUM, "linear extended state observer (Han 2009, Gao 2003)"),
    ObserverEntry("oracle", _KVARK, "the K-VARK filter given the simulator's true residual and rigid body"),
)
OBSERVER_NAMES = tuple(entry.name for entry in OBSERVERS)
OBSERVERS_BY_NAME = {entry.name: entry for entry in OBSERVERS}
