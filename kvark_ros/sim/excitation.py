"""Optimised random-Fourier excitation trajectories (paper v1 eqs. 24-25).

Each joint follows ``q_j(t) = q̄_j + w(t) Σ_κ [a_jκ sin(ω_κ t) + b_jκ cos(ω_κ t)]`` (eq. 24) with
K harmonics ω_κ between 0.1 and 2 Hz, each a whole number of cycles over the duration. The
window w(t) (a quintic smoothstep over ``ramp`` seconds at both ends) is ours: it makes the
motion start and end at rest at q̄, so a run begins from a still robot.

The coefficients θ = (a, b) maximise ``log det Cov(S(θ))`` (eq. 25, i.e. minimise J) of the
state cloud S = {(q, q̇, q̈)_t}, each coordinate normalised by its limit (this only shifts the
log-det by a constant), minus a penalty on position, velocity and acceleration limit
violations. Every coordinate of S is a combination of the 6K signals w·sin, w·cos, ẇ·sin, ẇ·cos,
ẅ·sin, ẅ·cos (``cloud_rank``), so a short trajectory (few whole cycles fit: K = 2 for a 1 s run)
has fewer than 3n of them and a singular Cov, whose determinant is rounding noise that differs
between numpy/BLAS releases; there the log-det is that of Cov on the directions S spans (the sum of
the logs of its ``cloud_rank`` largest eigenvalues). The optimiser is
``scipy.optimize.differential_evolution`` (the paper's GA); a final uniform scaling of the
coefficients (if needed) makes the returned trajectory strictly feasible on a 500 Hz grid.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import OptimizeResult, differential_evolution
from scipy.stats import qmc

from kvark_ros.core.estimation.linalg import single_threaded_blas
from kvark_ros.sim.robots import RobotSetup

FloatArray = npt.NDArray[np.float64]
F_MIN_HZ, F_MAX_HZ = 0.1, 2.0
PENALTY_WEIGHT = 100.0   # log-det units per unit of relative limit excess (summed over joints)
CHECK_RATE_HZ = 500.0    # grid on which the returned trajectory is made feasible
MAX_OBJECTIVE_SAMPLES = 1000   # cap on the objective grid, so long trajectories cost the same


def urdf_limits(model: Any, position_scale: float, velocity_scale: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(lower, upper, velocity) (n,): a pinocchio ``model``'s position limits shrunk about their midpoints by
    ``position_scale`` (rad) and its velocity limits × ``velocity_scale`` (rad/s): the box every excitation keeps in."""
    lower, upper = np.array(model.lowerPositionLimit), np.array(model.upperPositionLimit)
    mid, half = 0.5 * (upper + lower), 0.5 * (upper - lower) * position_scale
    return mid - half, mid + half, np.array(model.velocityLimit) * velocity_scale


@dataclass(frozen=True, eq=False)
class ExcitationLimits:
    """Box the excitation must stay in: q̄ ± half_range (rad), |q̇| ≤ velocity (rad/s),
    |q̈| ≤ acceleration (rad/s²); all (n,)."""

    centre: FloatArray
    half_range: FloatArray
    velocity: FloatArray
    acceleration: FloatArray

    @classmethod
    def for_robot(cls, setup: RobotSetup, position_scale: float = 0.8, velocity_scale: float = 0.5,
                  acceleration_scale: float = 0.5) -> ExcitationLimits:
        """URDF position and velocity limits (via pinocchio) and the setup's acceleration limits,
        each scaled by its safety factor; the position range shrinks about its midpoint and,
        if the setup has an excitation window, is intersected with home ± window."""
        lower, upper, velocity = urdf_limits(setup.nominal_model().model, position_scale, velocity_scale)
        if setup.excitation_half_range is not None:
            window = np.array(setup.excitation_half_range) * position_scale
            lower = np.maximum(lower, setup.home_array() - window)
            upper = np.minimum(upper, setup.home_array() + window)
        return cls(centre=0.5 * (upper + lower), half_range=0.5 * (upper - lower), velocity=velocity,
                   acceleration=np.array(setup.acceleration_limit) * acceleration_scale)

    def violation(self, q: FloatArray, qd: FloatArray, qdd: FloatArray) -> FloatArray:
        """Largest ratio |value|/limit per joint over position, velocity and acceleration: (…, n).
        Samples run along axis −2; ≤ 1 means within the limits."""
        ratios = (np.abs(q - self.centre).max(axis=-2) / self.half_range,
                  np.abs(qd).max(axis=-2) / self.velocity,
                  np.abs(qdd).max(axis=-2) / self.acceleration)
        return np.maximum(np.maximum(ratios[0], ratios[1]), ratios[2])


def harmonic_frequencies(duration: float, harmonics: int) -> FloatArray:
    """K frequencies (Hz), geometrically spaced in [0.1, 2] Hz and rounded to whole cycles over
    ``duration`` (the κ-th harmonic frequency "over the trajectory duration" of eq. 24)."""
    if duration <= 0.0 or harmonics < 1:
        raise ValueError(f"need duration > 0 s and harmonics >= 1, got {duration}, {harmonics}")
    cycles = np.floor(np.geomspace(F_MIN_HZ, F_MAX_HZ, harmonics) * duration + 0.5)
    return np.unique(np.maximum(cycles, 1.0)) / duration


def cloud_rank(n: int, harmonics: int, ramp: float) -> int:
    """How many directions the (q, q̇, q̈) cloud of an n-joint eq.-24 trajectory with ``harmonics`` frequencies
    can span: its 3n coordinates combine 6K signals (w, ẇ, ẅ times sin and cos), 2K without a fade window."""
    return min(3 * n, (6 if ramp > 0.0 else 2) * harmonics)


def _smoothstep(x: Any) -> tuple[Any, Any, Any]:
    """Quintic smoothstep on [0, 1] and its first two derivatives (floats or arrays)."""
    return x**3 * (10.0 - 15.0 * x + 6.0 * x**2), 30.0 * x**2 * (1.0 - x) ** 2, \
        60.0 * x * (1.0 - x) * (1.0 - 2.0 * x)


def _window(t: FloatArray, duration: float, ramp: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Fade-in/fade-out w(t) ∈ [0, 1] and its first two time derivatives for times t (T,) s.

    Each fade lasts ``ramp`` s; ramp ≤ duration/2, so the two never overlap.
    """
    w, wd, wdd = np.ones_like(t), np.zeros_like(t), np.zeros_like(t)
    if ramp > 0.0:
        fades = ((t < ramp, t / ramp, 1.0), (t > duration - ramp, (duration - t) / ramp, -1.0))
        for inside, x, sign in fades:
            s, sd, sdd = _smoothstep(np.clip(x[inside], 0.0, 1.0))
            w[inside], wd[inside], wdd[inside] = s, sign * sd / ramp, sdd / ramp**2
    return w, wd, wdd


def _window_at(t: float, duration: float, ramp: float) -> tuple[float, float, float]:
    """``_window`` at one time t s, without array overhead (the per-step controller path)."""
    if ramp > 0.0:
        for x, sign in ((t / ramp, 1.0), ((duration - t) / ramp, -1.0)):
            if x < 1.0:
                s, sd, sdd = _smoothstep(max(x, 0.0))
                return s, sign * sd / ramp, sdd / ramp**2
    return 1.0, 0.0, 0.0


@dataclass(frozen=True, eq=False)
class FourierTrajectory:
    """Eq. 24 with a fade window: centre (n,) rad, frequencies (K,) Hz, a and b (n, K) rad."""

    centre: FloatArray
    frequencies: FloatArray
    a: FloatArray
    b: FloatArray
    duration: float
    ramp: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.ramp <= 0.5 * self.duration:
            raise ValueError(f"ramp must lie in [0, duration/2] s, got {self.ramp} for {self.duration} s")

    def _evaluate(self, phase: FloatArray, w: Any, wd: Any,
                  wdd: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
        """q, q̇, q̈ from the phases ω_κ t (…, K) and the window (scalars or (…, 1))."""
        omega = 2.0 * np.pi * self.frequencies
        sin, cos = np.sin(phase), np.cos(phase)
        f = sin @ self.a.T + cos @ self.b.T
        fd = (cos * omega) @ self.a.T - (sin * omega) @ self.b.T
        fdd = -((sin * omega**2) @ self.a.T + (cos * omega**2) @ self.b.T)
        return self.centre + w * f, wd * f + w * fd, wdd * f + 2.0 * wd * fd + w * fdd

    def sample(self, t: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """q (rad), q̇ (rad/s), q̈ (rad/s²) at times t (T,) s, each (T, n); constant after the end."""
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.duration)
        w, wd, wdd = (x[:, None] for x in _window(t, self.duration, self.ramp))
        return self._evaluate(np.outer(t, 2.0 * np.pi * self.frequencies), w, wd, wdd)

    def __call__(self, t: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Reference (q, q̇, q̈), each (n,), at time t s: the controller interface."""
        t = min(max(t, 0.0), self.duration)
        return self._evaluate(2.0 * np.pi * self.frequencies * t, *_window_at(t, self.duration, self.ramp))


def log_det_coverage(q: FloatArray, qd: FloatArray, qdd: FloatArray, limits: ExcitationLimits,
                     rank: int) -> FloatArray:
    """``log det Cov`` of the normalised state cloud (−J of eq. 25); inputs (…, T, n), output (…).

    Each coordinate is divided by its limit, so values of different trajectories of the same robot
    compare directly. ``rank`` (``cloud_rank``) below 3n: the cloud spans only that many directions and the
    value is the log of the product of Cov's ``rank`` largest eigenvalues. −inf for a degenerate cloud.
    """
    cloud = np.concatenate([(q - limits.centre) / limits.half_range, qd / limits.velocity,
                            qdd / limits.acceleration], axis=-1)
    cloud = cloud - cloud.mean(axis=-2, keepdims=True)
    cov = np.swapaxes(cloud, -1, -2) @ cloud / (cloud.shape[-2] - 1)
    if rank >= cov.shape[-1]:
        sign, logdet = np.linalg.slogdet(cov)
        return np.where(sign > 0, logdet, -np.inf)
    spanned = np.linalg.eigvalsh(cov)[..., -rank:]                  # ascending: the rank largest
    logdet = np.log(np.maximum(spanned, np.finfo(float).tiny)).sum(axis=-1)
    return np.where(spanned[..., 0] > 0.0, logdet, -np.inf)


@dataclass(frozen=True, eq=False)
class ExcitationResult:
    """An optimised trajectory and how the optimisation went.

    logdet: −J (eq. 25) of the returned, feasible trajectory on the 500 Hz grid;
    initial_best_logdet: the best −J in the initial (Latin-hypercube) population, each member
        first shrunk into the limits as the result is: what no optimisation would give;
    scale: factor (≤ 1) applied to the optimiser's best coefficients to make them feasible;
    optimizer: scipy's result (its ``fun`` is the penalised −log-det on the coarse grid).
    """

    trajectory: FourierTrajectory
    logdet: float
    initial_best_logdet: float
    scale: float
    optimizer: OptimizeResult


class _Objective:
    """Penalised −log-det of eq. 25 for a batch of parameter vectors (vectorised for DE)."""

    def __init__(self, limits: ExcitationLimits, frequencies: FloatArray, duration: float,
                 ramp: float, sample_rate: float) -> None:
        self.limits = limits
        self.n, self.k = limits.centre.size, frequencies.size
        self.rank = cloud_rank(self.n, self.k, ramp)
        t = np.linspace(0.0, duration, min(int(duration * sample_rate), MAX_OBJECTIVE_SAMPLES) + 1)
        omega = 2.0 * np.pi * frequencies
        self.sin, self.cos = np.sin(np.outer(t, omega)), np.cos(np.outer(t, omega))
        self.omega = omega
        self.window = _window(t, duration, ramp)

    def split(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(2nK, S) parameters → a, b each (S, n, K)."""
        batch = theta.reshape(2, self.n, self.k, -1)
        return np.moveaxis(batch[0], -1, 0), np.moveaxis(batch[1], -1, 0)

    def scores(self, theta: FloatArray) -> FloatArray:
        """log-det minus limit penalty, (S,) for theta (2nK, S)."""
        logdet, ratio = self.evaluate(theta)
        return logdet - PENALTY_WEIGHT * np.clip(ratio - 1.0, 0.0, None).sum(axis=-1)

    def scaled_logdet(self, theta: FloatArray) -> FloatArray:
        """log-det (S,) of each candidate after shrinking it uniformly into the limits.

        Shrinking every coefficient by s scales every normalised coordinate by s, so the log-det (over
        ``rank`` directions) falls by exactly 2·rank·log(1/s)."""
        logdet, ratio = self.evaluate(theta)
        return logdet - 2 * self.rank * np.log(np.maximum(ratio.max(axis=-1), 1.0))

    def evaluate(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """log-det (S,) and per-joint limit ratios (S, n) for theta (2nK, S)."""
        a, b = self.split(theta)
        om = self.omega
        f = np.einsum("tk,snk->stn", self.sin, a) + np.einsum("tk,snk->stn", self.cos, b)
        fd = np.einsum("tk,snk->stn", self.cos * om, a) - np.einsum("tk,snk->stn", self.sin * om, b)
        fdd = -np.einsum("tk,snk->stn", self.sin * om**2, a) - np.einsum("tk,snk->stn", self.cos * om**2, b)
        w, wd, wdd = (x[None, :, None] for x in self.window)
        q = self.limits.centre + w * f
        qd, qdd = wd * f + w * fd, wdd * f + 2.0 * wd * fd + w * fdd
        return log_det_coverage(q, qd, qdd, self.limits, self.rank), self.limits.violation(q, qd, qdd)

    def __call__(self, theta: FloatArray) -> FloatArray:
        """What DE minimises: −score."""
        return -self.scores(theta.reshape(theta.shape[0], -1))


def optimise_excitation(limits: ExcitationLimits, duration: float, seed: int | np.random.Generator,
                        harmonics: int = 5, population: int = 24, generations: int = 60,
                        ramp: float = 1.0, sample_rate: float = 50.0) -> ExcitationResult:
    """Design one excitation trajectory (eqs. 24-25) with differential evolution.

    duration, ramp: s (ramp is shortened to a quarter of a short duration); population:
    candidates per generation; generations: DE iterations (the paper uses 50 and 100; the
    defaults take a few seconds); sample_rate: Hz of the grid the objective is evaluated on
    (at most 1000 points).
    Deterministic for a given seed.
    """
    rng = np.random.default_rng(seed)
    ramp = min(ramp, 0.25 * duration)
    frequencies = harmonic_frequencies(duration, harmonics)
    objective = _Objective(limits, frequencies, duration, ramp, sample_rate)
    omega = 2.0 * np.pi * frequencies
    # Amplitude at which one harmonic alone reaches a limit, per (joint, harmonic), rad; the
    # search box is half of it (a sum of K harmonics at full reach is mostly infeasible).
    reach = np.minimum(np.minimum(limits.half_range[:, None], limits.velocity[:, None] / omega),
                       limits.acceleration[:, None] / omega**2)
    upper = 0.5 * np.concatenate([reach.ravel(), reach.ravel()])
    bounds = np.stack([-upper, upper], axis=1)
    init = qmc.scale(qmc.LatinHypercube(d=upper.size, rng=rng).random(population), -upper, upper)
    initial_best = float(objective.scaled_logdet(init.T).max())
    # High crossover (0.9): the harmonics of all joints interact in the log-det, so trial vectors
    # that change many coefficients at once improve it faster (about twice SciPy's default 0.7).
    with single_threaded_blas():                    # small products: one BLAS thread is faster
        result = differential_evolution(objective, bounds, maxiter=generations, init=init, rng=rng,
                                        recombination=0.9, vectorized=True, updating="deferred",
                                        polish=False, tol=0.0)
    a, b = objective.split(result.x[:, None])
    trajectory = FourierTrajectory(limits.centre.copy(), frequencies, a[0], b[0], duration, ramp)
    grid = np.arange(int(duration * CHECK_RATE_HZ) + 1) / CHECK_RATE_HZ
    ratio = float(limits.violation(*trajectory.sample(grid)).max())
    scale = 1.0 if ratio <= 1.0 else 0.999 / ratio
    if scale < 1.0:
        trajectory = FourierTrajectory(limits.centre.copy(), frequencies, a[0] * scale, b[0] * scale,
                                       duration, ramp)
    logdet = float(log_det_coverage(*trajectory.sample(grid), limits, objective.rank))
    return ExcitationResult(trajectory, logdet, initial_best, scale, result)


def random_trajectory(limits: ExcitationLimits, duration: float, rng: np.random.Generator,
                      harmonics: int = 3, fraction: float = 0.5, ramp: float = 1.0) -> FourierTrajectory:
    """An unoptimised eq.-24 trajectory with random coefficients, scaled so its peak position,
    velocity or acceleration use ``fraction`` of the limits: plain joint-space motion."""
    ramp = min(ramp, 0.25 * duration)
    frequencies = harmonic_frequencies(duration, harmonics)
    n = limits.centre.size
    a, b = rng.standard_normal((2, n, frequencies.size))
    trajectory = FourierTrajectory(limits.centre.copy(), frequencies, a, b, duration, ramp)
    grid = np.arange(int(duration * CHECK_RATE_HZ) + 1) / CHECK_RATE_HZ
    factor = fraction / np.maximum(limits.violation(*trajectory.sample(grid)), 1e-12)   # per joint
    return FourierTrajectory(limits.centre.copy(), frequencies, a * factor[:, None], b * factor[:, None],
                             duration, ramp)
