"""Seed-004 baselines (momentum, kfmo, sh_akfmo, vbkfmo_q, eso): known answers on synthetic momentum streams.

The stream is the observers' own model (M1): ``p_k = p_{k−1} + h_k (u_{k−1} + τ_ext) + w`` measured
with white noise, so every answer below is exact or has a stated tolerance.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import pytest
from scipy.linalg import expm

from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise, torque_density_for_bandwidth
from kvark_ros.core.estimation.observers.momentum_observers import (
    MOMENTUM_OBSERVER_NAMES, ExtendedStateObserver, KFMomentumObserver, MomentumObserver, SageHusaKFMomentumObserver,
    VBKFMomentumObserver, make_momentum_observer)

KF_NAMES = ("kfmo", "sh_akfmo", "vbkfmo_q")
TAU = np.array([3.0, -2.0, 1.5, 2.0, -1.0, 0.8, 0.5])        # N·m


@dataclass
class Stream:
    t: np.ndarray      # (T+1,) sample times, s
    h: np.ndarray      # (T,) actual steps
    u: np.ndarray      # (T, n) u_{k}, held over interval k
    p: np.ndarray      # (T+1, n) measured momentum
    tau: np.ndarray    # (T, n) true τ_ext over interval k (the estimate after step k is compared with it)


def momentum_stream(tau_of_t: Callable[[float], np.ndarray], n: int = 7, steps: int = 2000, dt: float = 1e-3,
                    jitter: float = 0.0, sigma_p: float = 0.0, model_density: float = 0.0,
                    seed: int = 0, u_std: float = 5.0) -> Stream:
    rng = np.random.default_rng(seed)
    h = dt * (1.0 + jitter * rng.uniform(-1.0, 1.0, steps))
    t = np.concatenate([[0.0], np.cumsum(h)])
    u = rng.normal(0.0, u_std, (steps, n))
    tau = np.array([tau_of_t(tk) for tk in t[:-1]]).reshape(steps, n)
    w = np.sqrt(model_density * h)[:, None] * rng.standard_normal((steps, n))
    p = np.zeros((steps + 1, n))
    p[1:] = np.cumsum(h[:, None] * (u + tau) + w, axis=0)
    return Stream(t, h, u, p + sigma_p * rng.standard_normal(p.shape), tau)


def run(observer, s: Stream, dt_override: float | None = None) -> tuple[np.ndarray, list]:
    qd = np.zeros(s.p.shape[1])
    estimates, covariances = [], []
    for k in range(len(s.h)):
        x, P = observer.step(s.h[k] if dt_override is None else dt_override, qd, s.p[k + 1], s.p[k], s.u[k])
        estimates.append(x.copy())
        covariances.append(None if P is None else P.copy())
    return np.array(estimates), covariances


def constant(torque: np.ndarray) -> Callable[[float], np.ndarray]:
    return lambda t: torque


def step_at(start: float, torque: np.ndarray) -> Callable[[float], np.ndarray]:
    return lambda t: torque if t >= start - 1e-12 else np.zeros_like(torque)


def switch_time(s: Stream, start: float) -> float:
    """The sample instant at which ``step_at(start, …)`` switches on (the first t_k ≥ start)."""
    return float(s.t[np.argmax(s.t >= start - 1e-12)])


def rise_time(estimate: np.ndarray, s: Stream, start: float, torque: np.ndarray, level: float = 0.9) -> np.ndarray:
    """Per joint, time after ``start`` until the estimate first reaches ``level`` of the step."""
    i = np.searchsorted(s.t[1:], start + 1e-12)
    reached = estimate[i:] / torque >= level
    return np.where(reached.any(axis=0), s.t[1:][i + np.argmax(reached, axis=0)] - start, np.inf)


# --------------------------------------------------------------------------------------------
# Registry and interface
# --------------------------------------------------------------------------------------------

def test_registry_builds_every_observer_from_the_config(panda_config):
    assert MOMENTUM_OBSERVER_NAMES == ("momentum", "kfmo", "sh_akfmo", "vbkfmo_q", "eso")
    for name in MOMENTUM_OBSERVER_NAMES:
        observer = make_momentum_observer(name, 7, None, panda_config.filter)
        assert observer.name == name and observer.n == 7
        assert observer.uses_residual_model is False
        x, P = observer.step(0.001, np.zeros(7), np.ones(7), np.zeros(7), np.zeros(7))
        assert x.shape == (7,)
        assert observer.reports_covariance == (name in KF_NAMES) == (P is not None)
        if P is not None:
            assert P.shape == (7, 7)
    settings = panda_config.filter
    assert make_momentum_observer("kfmo", 7, None, settings).initial_covariance == settings.initial_covariance
    assert make_momentum_observer("vbkfmo_q", 7, None, settings).iterations == settings.vb_iterations
    assert np.all(make_momentum_observer("momentum", 7, None, settings, gain=10.0).gain == 10.0)
    with pytest.raises(ValueError, match="unknown momentum observer"):
        make_momentum_observer("nope", 7, None, settings)
    with pytest.raises(ValueError, match="joints"):
        make_momentum_observer("kfmo", 6, MomentumNoise.default(7))


def test_configure_takes_the_run_time_keys_only(panda_config):
    """An observer keeps the filter settings it was built with; configure changes run-time keys only."""
    settings = panda_config.filter
    observer = make_momentum_observer("kfmo", 7, None, settings)
    assert observer.settings is settings
    observer.configure(replace(settings, ewma_time=0.04, nis_time=0.01))
    assert observer.settings.ewma_time == 0.04 and observer.settings.nis_time == 0.01
    with pytest.raises(ValueError, match="filter.initial_covariance"):
        observer.configure(replace(settings, initial_covariance=2.0))
    assert observer.settings.initial_covariance == settings.initial_covariance
    with pytest.raises(ValueError, match="without filter settings"):
        make_momentum_observer("kfmo", 7).configure(settings)


def test_reset_restarts_and_outputs_are_never_modified_afterwards():
    s = momentum_stream(step_at(0.02, TAU), steps=100, jitter=0.2, sigma_p=1e-3, seed=4)
    for name in MOMENTUM_OBSERVER_NAMES:
        observer = make_momentum_observer(name, 7)
        qd = np.zeros(7)
        kept = [observer.step(s.h[k], qd, s.p[k + 1], s.p[k], s.u[k]) for k in range(50)]
        copies = [(x.copy(), None if P is None else P.copy()) for x, P in kept]
        for (x, P), (x0, P0) in zip(kept, copies):
            assert np.array_equal(x, x0) and (P is None or np.array_equal(P, P0)), name
        observer.reset()
        again = [observer.step(s.h[k], qd, s.p[k + 1], s.p[k], s.u[k])[0] for k in range(50)]
        assert np.array_equal(np.array(again), np.array([x for x, _ in copies])), name


# --------------------------------------------------------------------------------------------
# Convergence to a constant external torque
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", MOMENTUM_OBSERVER_NAMES)
def test_noise_free_stream_converges_to_the_constant_torque(name):
    """ṗ = u + τ_ext (our sign): a momentum growing faster than u is a positive τ_ext. Error < 1e-6 N·m."""
    s = momentum_stream(constant(TAU), steps=3000)
    estimate, _ = run(make_momentum_observer(name, 7), s)
    assert np.max(np.abs(estimate[-1] - TAU)) < 1e-6


@pytest.mark.parametrize("name", MOMENTUM_OBSERVER_NAMES)
def test_noisy_stream_converges_to_the_constant_torque(name):
    """σ_p = 1e-3 N·m·s momentum noise and model noise at the default density: mean of the last
    second within 0.03 N·m of τ_ext on every joint (kfmo's steady-state std is ≈ 0.008 N·m)."""
    noise = MomentumNoise.default(7)
    s = momentum_stream(constant(TAU), steps=3000, sigma_p=np.sqrt(noise.momentum_variance[0]),
                        model_density=noise.model_density[0], seed=1)
    estimate, _ = run(make_momentum_observer(name, 7, noise), s)
    assert np.max(np.abs(estimate[-1000:].mean(axis=0) - TAU)) < 0.03


@pytest.mark.parametrize("name", MOMENTUM_OBSERVER_NAMES)
def test_jittered_steps_are_used_as_given(name):
    """Steps alternate 0.5 / 1.5 ms with |u| ≈ 20 N·m: only an observer that uses the actual step
    converges (< 1e-6 N·m); fed the nominal 1 ms instead, the same data gives errors > 0.1 N·m."""
    s = momentum_stream(constant(TAU), steps=3000, u_std=20.0)
    s.h = np.where(np.arange(len(s.h)) % 2 == 0, 0.5e-3, 1.5e-3)
    s.t = np.concatenate([[0.0], np.cumsum(s.h)])
    s.p[1:] = np.cumsum(s.h[:, None] * (s.u + s.tau), axis=0)
    estimate, _ = run(make_momentum_observer(name, 7), s)
    assert np.max(np.abs(estimate[-1] - TAU)) < 1e-6
    nominal, _ = run(make_momentum_observer(name, 7), s, dt_override=1e-3)
    assert np.max(np.abs(nominal[-500:] - TAU)) > 0.1


# --------------------------------------------------------------------------------------------
# Momentum observer and ESO: analytic step responses
# --------------------------------------------------------------------------------------------

def test_momentum_observer_follows_the_first_order_step_response():
    gain, start = 50.0, 0.2
    s = momentum_stream(step_at(start, TAU), steps=600, jitter=0.3, seed=2)
    exact, _ = run(MomentumObserver(7, gain=gain), s)
    start = switch_time(s, start)
    after = s.t[1:] > start
    elapsed = (s.t[1:] - start)[after]
    expected = TAU * (1.0 - np.exp(-gain * elapsed))[:, None]           # r = τ (1 − e^{−K_O t}) at every sample
    assert np.allclose(exact[after], expected, rtol=0.0, atol=1e-9)
    assert np.allclose(exact[~after], 0.0, atol=1e-9)

    s = momentum_stream(step_at(start, TAU), steps=600, seed=2)        # 1 kHz, K_O h = 0.05
    euler, _ = run(MomentumObserver(7, gain=gain, discretization="euler"), s)
    i = np.searchsorted(s.t[1:], start + 1.0 / gain - 1e-9)            # t = 1/K_O after the step
    assert np.allclose(euler[i] / TAU, 1.0 - np.exp(-1.0), rtol=0.02)   # 0.632 within 2 %


def test_euler_momentum_observer_is_the_integral_form():
    """(M4) is r_k = K_O (p_k − p_0 − Σ_{j<k} h_j (u_j + r_j)), computed here independently."""
    gain = np.linspace(20.0, 80.0, 7)
    s = momentum_stream(step_at(0.05, TAU), steps=300, jitter=0.3, sigma_p=1e-3, seed=3)
    estimate, _ = run(MomentumObserver(7, gain=gain, discretization="euler"), s)
    r, integral = np.zeros(7), np.zeros(7)
    for k in range(len(s.h)):
        integral += s.h[k] * (s.u[k] + r)
        r = gain * (s.p[k + 1] - s.p[0] - integral)
        assert np.allclose(estimate[k], r, rtol=1e-9, atol=1e-9)


def test_eso_has_the_critically_damped_step_response_at_every_sample():
    omega, start = 80.0, 0.1
    s = momentum_stream(step_at(start, TAU), steps=500, jitter=0.3, seed=5)
    estimate, _ = run(ExtendedStateObserver(7, bandwidth=omega), s)
    start = switch_time(s, start)
    after = s.t[1:] > start
    wt = omega * (s.t[1:] - start)[after]
    expected = TAU * (1.0 - (1.0 + wt) * np.exp(-wt))[:, None]          # ω²/(s + ω)² step response
    assert np.allclose(estimate[after], expected, rtol=0.0, atol=1e-8)
    assert np.allclose(estimate[~after], 0.0, atol=1e-8)
    assert ExtendedStateObserver(7).omega[0] == 80.0


def test_eso_tracks_its_momentum_state():
    s = momentum_stream(step_at(0.1, TAU), steps=800, seed=6)
    observer = ExtendedStateObserver(7)
    run(observer, s)
    assert np.allclose(observer.p_hat, s.p[-1], atol=1e-9)             # p̂ → p once τ̂ has converged


# --------------------------------------------------------------------------------------------
# Kalman filters against textbook matrix implementations
# --------------------------------------------------------------------------------------------

def van_loan(h: float, q_p: np.ndarray, q_tau: np.ndarray) -> np.ndarray:
    """Q_d of ẋ = [[0, I], [0, 0]] x + w, w ~ diag(q_p, q_τ) density, by Van Loan's matrix exponential."""
    n = len(q_p)
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    W = np.diag(np.concatenate([q_p, q_tau]))
    block = np.block([[-A, W], [np.zeros_like(A), A.T]]) * h
    E = expm(block)
    F = E[2 * n:, 2 * n:].T
    return F @ E[: 2 * n, 2 * n:]


def q_d(h: float, q_p: np.ndarray, q_tau: np.ndarray) -> np.ndarray:
    """(K2)'s Q_d as a 2n × 2n matrix (pinned to Van Loan's by the test below)."""
    return np.block([[np.diag(q_p * h + q_tau * h ** 3 / 3.0), np.diag(q_tau * h ** 2 / 2.0)],
                     [np.diag(q_tau * h ** 2 / 2.0), np.diag(q_tau * h)]])


def test_process_noise_is_van_loans_discretisation():
    noise = MomentumNoise(np.ones(3), np.array([5e-3, 2e-2, 1.0]), np.array([1e-6, 0.0, 3e-2]))
    observer = KFMomentumObserver(3, noise)
    for h in (1e-4, 1e-3, 2.7e-3, 0.05):
        reference = van_loan(h, noise.model_density, noise.torque_density)
        assert np.allclose(q_d(h, noise.model_density, noise.torque_density), reference, rtol=1e-9, atol=1e-15)
        qa, qb, qc = observer.process_noise(h)
        assert np.allclose(np.concatenate([qa, qb, qc]),
                           np.concatenate([np.diag(reference[:3, :3]), np.diag(reference[:3, 3:]),
                                           np.diag(reference[3:, 3:])]), rtol=1e-9, atol=1e-15)


def test_kfmo_is_the_textbook_2n_state_kalman_filter():
    n = 3
    noise = MomentumNoise(np.array([1e-6, 4e-6, 2e-7]), np.array([5e-3, 2e-2, 1e-3]), np.array([1e-6, 0.0, 3e-6]))
    s = momentum_stream(step_at(0.1, TAU[:n]), n=n, steps=400, jitter=0.3, sigma_p=1e-3, model_density=1e-6, seed=7)
    estimate, covariance = run(KFMomentumObserver(n, noise, initial_covariance=2.0), s)
    H = np.hstack([np.eye(n), np.zeros((n, n))])
    x = np.concatenate([s.p[0], np.zeros(n)])
    P = np.diag(np.concatenate([noise.momentum_variance, np.full(n, 2.0)]))
    R = np.diag(noise.momentum_variance)
    for k in range(len(s.h)):
        h = s.h[k]
        F = np.block([[np.eye(n), h * np.eye(n)], [np.zeros((n, n)), np.eye(n)]])
        x = F @ x + np.concatenate([h * s.u[k], np.zeros(n)])
        P = F @ P @ F.T + q_d(h, noise.model_density, noise.torque_density)
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x = x + K @ (s.p[k + 1] - H @ x)
        P = (np.eye(2 * n) - K @ H) @ P
        assert np.allclose(estimate[k], x[n:], rtol=1e-7, atol=1e-9)
        assert np.allclose(covariance[k], P[n:, n:], rtol=1e-7, atol=1e-12)


def test_vbkfmo_q_is_huangs_algorithm_per_joint():
    """Huang et al. (2018) Algorithm 1 with R fixed, in matrix form for each joint's 2-state filter."""
    n, tau_w, iterations = 2, 8.0, 4
    noise = MomentumNoise(np.array([1e-6, 4e-6]), np.array([5e-3, 2e-2]), np.array([1e-6, 0.0]))
    s = momentum_stream(step_at(0.1, TAU[:n]), n=n, steps=200, jitter=0.3, sigma_p=1e-3, seed=8)
    estimate, covariance = run(VBKFMomentumObserver(n, noise, iterations=iterations, tau=tau_w), s)
    H = np.array([[1.0, 0.0]])
    d = 2
    for j in range(n):
        x = np.array([s.p[0, j], 0.0])
        P = np.diag([noise.momentum_variance[j], 1.0])
        R = noise.momentum_variance[j]
        for k in range(len(s.h)):
            h = s.h[k]
            F = np.array([[1.0, h], [0.0, 1.0]])
            x_pred = F @ x + np.array([h * s.u[k, j], 0.0])
            P_nom = F @ P @ F.T + q_d(h, noise.model_density[j:j + 1], noise.torque_density[j:j + 1])
            t_hat, T_hat = d + tau_w + 1.0, tau_w * P_nom
            x, P = x_pred, P_nom
            for _ in range(iterations):
                e = x - x_pred
                T, t = T_hat + P + np.outer(e, e), t_hat + 1.0
                P_pred = np.linalg.inv((t - d - 1.0) * np.linalg.inv(T))    # E[P⁻¹]⁻¹, Huang's expectation
                K = P_pred @ H.T / (H @ P_pred @ H.T + R)
                x = x_pred + (K * (s.p[k + 1, j] - x_pred[0])).ravel()
                P = (np.eye(2) - K @ H) @ P_pred
            assert np.isclose(estimate[k, j], x[1], rtol=1e-7, atol=1e-9)
            assert np.isclose(covariance[k][j, j], P[1, 1], rtol=1e-7, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Adaptation
# --------------------------------------------------------------------------------------------

def test_sh_akfmo_tracks_a_step_much_faster_than_kfmo_when_q_is_too_small():
    """q_τ 10⁴× too small: kfmo's bandwidth drops 10× (90 % after > 1 s); Sage-Husa inflates q̂_τ
    on the inconsistent innovations and reaches 90 % in under a fifth of kfmo's time."""
    base = MomentumNoise.default(7)
    small = MomentumNoise(base.momentum_variance, base.torque_density * 1e-4, base.model_density)
    s = momentum_stream(step_at(1.0, TAU), steps=4000, sigma_p=1e-3, model_density=1e-6, seed=9)
    fixed, _ = run(make_momentum_observer("kfmo", 7, small), s)
    sage_husa = make_momentum_observer("sh_akfmo", 7, small)
    adaptive, _ = run(sage_husa, s)
    t_fixed, t_adaptive = rise_time(fixed, s, 1.0, TAU), rise_time(adaptive, s, 1.0, TAU)
    assert np.all(t_fixed > 1.0)
    assert np.all(t_adaptive < 0.2 * t_fixed)
    assert np.all(sage_husa.q_tau_hat > 100.0 * small.torque_density)
    assert np.max(np.abs(adaptive[-500:].mean(axis=0) - TAU)) < 0.03


@pytest.mark.parametrize("scale", [1e-2, 1e2])
def test_sh_akfmo_learns_the_torque_random_walk_density(scale):
    """τ_ext a true random walk of density q_τ; starting 100× off, q̂_τ ends within a factor 4."""
    n, q_tau, steps = 3, 8.75e-3, 20000
    rng = np.random.default_rng(10)
    walk = np.cumsum(np.sqrt(q_tau * 1e-3) * rng.standard_normal((steps, n)), axis=0)
    s = momentum_stream(lambda t: walk[min(int(round(t / 1e-3)), steps - 1)], n=n, steps=steps,
                        sigma_p=1e-3, model_density=1e-6, seed=11)
    start = MomentumNoise(np.full(n, 1e-6), np.full(n, q_tau * scale), np.full(n, 1e-6))
    observer = SageHusaKFMomentumObserver(n, start)
    history = []
    for k in range(steps):
        observer.step(s.h[k], np.zeros(n), s.p[k + 1], s.p[k], s.u[k])
        history.append(observer.q_tau_hat)
    ratio = np.median(np.array(history[-2000:]), axis=0) / q_tau
    assert np.all((ratio > 0.25) & (ratio < 4.0)), ratio


def test_sh_akfmo_learns_the_momentum_noise_when_adapting_r():
    """adapt_r: R̂ from 10× too large to within 20 % of the true R (median of the last 2 s)."""
    n, R = 3, 1e-6
    s = momentum_stream(constant(TAU[:n]), n=n, steps=8000, sigma_p=np.sqrt(R), model_density=1e-6, seed=12)
    noise = MomentumNoise.default(n)
    wrong = MomentumNoise(noise.momentum_variance * 10.0, noise.torque_density, noise.model_density)
    observer = SageHusaKFMomentumObserver(n, wrong, adapt_q=False, adapt_r=True)
    history = []
    for k in range(len(s.h)):
        observer.step(s.h[k], np.zeros(n), s.p[k + 1], s.p[k], s.u[k])
        history.append(observer.R_hat)
    assert np.allclose(np.median(np.array(history[-2000:]), axis=0), R, rtol=0.2)


def test_vbkfmo_q_covariance_reacts_to_an_unexpected_step():
    """Huang's VB inflates P⁻ on inconsistent innovations: in the 200 ms after a step the reported
    τ_ext variance rises, by > 2.5× where the step is ≥ 2 N·m (> 1.2× for the 0.5 N·m one), while
    kfmo's P does not depend on the data at all. On a stream that matches its model, VB stays
    within 10 % of kfmo's error."""
    s = momentum_stream(step_at(1.0, TAU), steps=1500, sigma_p=1e-3, model_density=1e-6, seed=13)
    _, vb_cov = run(make_momentum_observer("vbkfmo_q", 7), s)
    _, kf_cov = run(make_momentum_observer("kfmo", 7), s)
    i = np.searchsorted(s.t[1:], 1.0 - 1e-12)
    vb_var = np.array([np.diag(P) for P in vb_cov])
    kf_var = np.array([np.diag(P) for P in kf_cov])
    rise = vb_var[i:i + 200].max(axis=0) / vb_var[i - 1]
    assert np.all(rise > 1.2) and np.all(rise[np.abs(TAU) >= 2.0] > 2.5), rise
    assert np.allclose(kf_var[i:i + 200], kf_var[i - 1], rtol=1e-9)

    steady = momentum_stream(constant(TAU), steps=3000, sigma_p=1e-3, model_density=1e-6, seed=14)
    vb, _ = run(make_momentum_observer("vbkfmo_q", 7), steady)
    kf, _ = run(make_momentum_observer("kfmo", 7), steady)
    rms = lambda e: np.sqrt(np.mean(e[1000:] ** 2))                    # noqa: E731
    assert rms(vb - TAU) < 1.1 * rms(kf - TAU)


# --------------------------------------------------------------------------------------------
# Covariance health
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, options", [("kfmo", {}), ("sh_akfmo", {}), ("sh_akfmo", {"adapt_r": True}),
                                           ("vbkfmo_q", {"iterations": 5, "tau": 1.0})])
def test_covariance_stays_symmetric_positive_definite_for_ten_thousand_noisy_steps(name, options):
    """10⁴ steps, jittered dt, ±5 N·m steps every 2 s, a tiny R and a large P_0 (stiff numerics)."""
    flips = lambda t: TAU * (5.0 if int(t / 2.0) % 2 else -5.0)       # noqa: E731
    s = momentum_stream(flips, steps=10000, jitter=0.4, sigma_p=1e-3, model_density=1e-4, seed=15)
    noise = MomentumNoise(np.full(7, 1e-10), np.full(7, 1e-2), np.full(7, 1e-6))
    observer = make_momentum_observer(name, 7, noise, initial_covariance=100.0, **options)
    qd, P = np.zeros(7), None
    for k in range(len(s.h)):
        x, P = observer.step(s.h[k], qd, s.p[k + 1], s.p[k], s.u[k])
        a, b, c = observer.a, observer.b, observer.c                     # every joint's 2×2 block, every step
        assert (a > 0.0).all() and (c > 0.0).all() and (a * c > b * b).all(), k
        if k % 100 == 0:
            assert np.all(np.isfinite(x)) and np.array_equal(P, P.T)
            np.linalg.cholesky(P)
    np.linalg.cholesky(P)
    assert np.all(np.linalg.eigvalsh(observer.covariance_blocks()) > 0.0)


# --------------------------------------------------------------------------------------------
# Noise model
# --------------------------------------------------------------------------------------------

def test_from_training_recovers_the_noise_variances():
    """R on every joint and q_p where it is resolvable, within 20 %; a smooth disturbance (offset,
    viscous friction, sinusoid) and ±20 % jitter do not bias them. Joint 0 has no model noise and
    R ≫ q_p h: q_p is reported as 0."""
    n, steps = 3, 20000
    rng = np.random.default_rng(16)
    R = np.array([1e-6, 1e-9, 4e-8])
    q_p = np.array([0.0, 2.5e-6, 1e-5])
    h = 1e-3 * (1.0 + 0.2 * rng.uniform(-1.0, 1.0, steps - 1))
    stamp = np.concatenate([[0.0], np.cumsum(h)])
    qd = np.sin(2.0 * np.pi * 0.5 * stamp)[:, None] * np.array([1.0, 0.5, 2.0])
    disturbance = 2.0 - 0.3 * qd + 0.5 * np.sin(2.0 * np.pi * 3.0 * stamp)[:, None]
    u = rng.normal(0.0, 5.0, (steps, n))
    model_noise = np.sqrt(q_p * h[:, None]) * rng.standard_normal((steps - 1, n))
    increments = h[:, None] * (u[:-1] + disturbance[:-1]) + model_noise
    p = np.vstack([np.zeros((1, n)), np.cumsum(increments, axis=0)]) + np.sqrt(R) * rng.standard_normal((steps, n))
    noise = MomentumNoise.from_training(p, u, stamp)
    assert np.allclose(noise.momentum_variance, R, rtol=0.2)
    assert noise.model_density[0] == 0.0
    assert np.allclose(noise.model_density[1:], q_p[1:], rtol=0.2)
    expected = torque_density_for_bandwidth(noise.momentum_variance, noise.model_density, float(np.median(h)), 50.0)
    assert np.allclose(noise.torque_density, expected)
    # bandwidth rule: with q_p = 0, q_τ = ω⁴ R h (natural frequency ω of the steady-state KF)
    assert np.isclose(noise.torque_density[0], 50.0 ** 4 * noise.momentum_variance[0] * np.median(h))


def test_from_training_is_safe_on_noise_free_data_and_rejects_bad_input():
    s = momentum_stream(constant(TAU), steps=500)
    noise = MomentumNoise.from_training(s.p, np.vstack([s.u, s.u[-1:]]), s.t)
    assert np.all(noise.momentum_variance > 0.0) and np.all(noise.torque_density > 0.0)
    with pytest.raises(ValueError, match="shape"):
        MomentumNoise.from_training(s.p, s.u, s.t)
    with pytest.raises(ValueError, match="increasing"):
        MomentumNoise.from_training(s.p, np.vstack([s.u, s.u[-1:]]), s.t[::-1])
    with pytest.raises(ValueError, match="at least"):
        MomentumNoise.from_training(s.p[:10], s.p[:10], s.t[:10])


def test_momentum_noise_validation_defaults_and_round_trip():
    noise = MomentumNoise.default(7)
    assert noise.n == 7 and np.all(noise.model_density > 0.0)
    assert np.allclose(noise.torque_density,
                       50.0 ** 2 * (50.0 ** 2 * noise.momentum_variance * 1e-3 + noise.model_density))
    assert MomentumNoise.from_dict(noise.to_dict()).to_dict() == noise.to_dict()
    assert np.all(MomentumNoise(np.ones(2), np.ones(2)).model_density == 0.0)
    with pytest.raises(ValueError, match="momentum_variance"):
        MomentumNoise(np.array([1.0, -1.0]), np.ones(2))
    with pytest.raises(ValueError, match="torque_density"):
        MomentumNoise(np.ones(2), np.zeros(2))
    with pytest.raises(ValueError, match="one entry per joint"):
        MomentumNoise(np.ones(2), np.ones(3))
    with pytest.raises(ValueError):
        noise.momentum_variance[0] = 2.0                                 # frozen, read-only arrays
