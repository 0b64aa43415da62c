"""A synthetic arm stream with known friction and external torque, from the pinocchio model alone.

Used by ``kvark bench``, ``kvark soak`` and the tests: the joint trajectory is prescribed (sums of
sines), and the commanded torque follows from the dynamics ``M q̈ + C q̇ + g + τ_f = τ_m + τ_ext``
(docs/method.md §1.2), so the true external torque is known exactly. The MuJoCo simulator
(``kvark_ros.sim``) is the realistic plant; this stream needs no extra dependency.
``train_synthetic`` trains a model on such streams.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import train_model

# Gaz et al., RA-L 2019, Panda joint friction (docs/method.md §10): τ_f = φ1/(1+e^{−φ2(q̇+φ3)}) − φ1/(1+e^{−φ2 φ3})
GAZ_PHI1 = np.array([0.54615, 0.87224, 0.64068, 1.2794, 0.83904, 0.30301, 0.56489])        # N·m
GAZ_PHI2 = np.array([5.1181, 9.0657, 10.136, 5.5903, 8.3469, 17.133, 10.336])            # s/rad
GAZ_PHI3 = np.array([0.039533, 0.025882, -0.04607, 0.036194, 0.026226, -0.021047, 0.0035526])  # rad/s


def gaz_friction(qd: np.ndarray) -> np.ndarray:
    """Gaz sigmoid friction (N·m) for (…, n) velocities, n ≤ 7 (the Panda's first n joints)."""
    n = qd.shape[-1]
    phi1, phi2, phi3 = GAZ_PHI1[:n], GAZ_PHI2[:n], GAZ_PHI3[:n]
    return phi1 / (1.0 + np.exp(-phi2 * (qd + phi3))) - phi1 / (1.0 + np.exp(-phi2 * phi3))


@dataclass(frozen=True)
class SyntheticStream:
    """Samples at a fixed rate: stamp (T,) s; q, qd, qdd, tau_m, tau_ext, friction (T, n)."""

    stamp: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_m: np.ndarray
    tau_ext: np.ndarray
    friction: np.ndarray


def step_torque(start: float, torque: np.ndarray) -> Callable[[float], np.ndarray]:
    """An external joint torque that switches on at ``start`` s and stays."""
    return lambda t: torque if t >= start else np.zeros_like(torque)


def synthetic_stream(robot: RobotModel, duration: float, rate: float = 500.0, seed: int = 0,
                     external: Callable[[float], np.ndarray] | None = None,
                     torque_noise_std: float = 0.02, amplitude: float = 0.5) -> SyntheticStream:
    """Sum-of-sines motion about a bent home pose with Gaz friction, torque noise and ``external`` τ_ext."""
    rng = np.random.default_rng(seed)
    n = robot.n
    stamp = np.arange(int(round(duration * rate))) / rate
    home = np.clip(0.5 * (robot.model.lowerPositionLimit + robot.model.upperPositionLimit), -1.5, 1.5)
    frequencies = rng.uniform(0.1, 0.6, size=(3, n))                  # Hz
    phases = rng.uniform(0.0, 2.0 * np.pi, size=(3, n))
    amplitudes = amplitude * rng.uniform(0.3, 1.0, size=(3, n)) / 3.0    # rad
    omega = 2.0 * np.pi * frequencies
    arg = omega[None] * stamp[:, None, None] + phases[None]
    q = home + np.sum(amplitudes * np.sin(arg), axis=1)
    qd = np.sum(amplitudes * omega * np.cos(arg), axis=1)
    qdd = -np.sum(amplitudes * omega ** 2 * np.sin(arg), axis=1)
    friction = gaz_friction(qd)
    tau_ext = np.zeros_like(q) if external is None else np.array([external(t) for t in stamp])
    tau_m = np.array([robot.inverse_dynamics(q[k], qd[k], qdd[k]) for k in range(len(stamp))])
    tau_m += friction - tau_ext + torque_noise_std * rng.standard_normal(q.shape)
    return SyntheticStream(stamp, q, qd, qdd, tau_m, tau_ext, friction)


def train_synthetic(robot: RobotModel, robot_name: str, seed: int = 0, duration: float = 20.0,
                    baselines: bool = True, rate: float = 500.0) -> TrainedModel:
    """The trainer of ``kvark train``, on two synthetic contact-free streams instead of bags.

    The streams' residual is Gaz friction, a function of q̇ alone, so every joint takes q̇ alone (the paper's
    KMP) and the per-joint input selection, which would only cost time, is skipped."""
    segments = []
    for offset in range(2):
        stream = synthetic_stream(robot, duration / 2, rate=rate, seed=seed + 1000 * offset)
        segments.append(EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0))
    return train_model(robot, robot_name, segments, baselines=baselines, seed=seed, log=lambda _line: None,
                       info={"source": "synthetic stream"}, residual_inputs="qd")
