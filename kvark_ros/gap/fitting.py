"""The least-squares core of ``kvark diagnose``: the gap on a set of effects, bounded and weighted, with the
Gaussian priors toward the URDF of payload and link inertia (docs/method.md §8.3)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import lsq_linear

from kvark_ros.gap.effects import Priors, Signals, Term


def long_run_covariance(scores: np.ndarray) -> np.ndarray:
    """Σ_l w_l Σ_t s_t s_{t−l}ᵀ (p, p) of a score series (T, p), Bartlett weights w_l = 1 − |l|/(L + 1) (Newey &
    West 1987; positive semi-definite), L by Andrews' (1991) AR(1) plug-in rule for that kernel:
    L = 1.1447 (α T)^{1/3}, α = Σ_a 4 ρ_a² σ_a⁴ / ((1 − ρ_a)⁶ (1 + ρ_a)²) / Σ_a σ_a⁴ / (1 − ρ_a)⁴ over the columns,
    ρ_a and σ_a² each column's lag-one regression coefficient and residual variance (ρ_a within ±0.99, L < T)."""
    count = len(scores)
    lead, lag = scores[1:], scores[:-1]
    rho = np.clip(np.sum(lead * lag, axis=0) / np.maximum(np.sum(lag * lag, axis=0), 1e-300), -0.99, 0.99)
    sigma4 = np.square(np.mean(np.square(lead - rho * lag), axis=0))
    alpha = (np.sum(4.0 * rho ** 2 * sigma4 / ((1.0 - rho) ** 6 * (1.0 + rho) ** 2))
             / max(float(np.sum(sigma4 / (1.0 - rho) ** 4)), 1e-300))
    bandwidth = min(int(np.ceil(1.1447 * (alpha * count) ** (1.0 / 3.0))), count - 1)
    total = scores.T @ scores
    for lag_count in range(1, bandwidth + 1):
        cross = scores[lag_count:].T @ scores[:-lag_count]
        total += (1.0 - lag_count / (bandwidth + 1.0)) * (cross + cross.T)
    return total


class Fitter:
    """Bounded weighted least squares of the gap on a set of terms, within ``priors``.

    ``nuisance``: terms fitted with every set but never selected, reported or written (the unknown centre of mass and
    inertia of a known-load calibration's load, ``gap.known_load``); their parameters follow the terms' in θ, G⁻¹ and
    the covariance, so a term's slice is where it always was. ``forced``: terms every selection starts from and
    keeps (``gap.selection``: a known-load calibration's drive gains)."""

    def __init__(self, train: Signals, held: Signals, weights: np.ndarray, priors: Priors) -> None:
        self.train, self.held, self.w, self.priors = train, held, weights, priors
        self.prior_scale: dict[str, np.ndarray] = {}   # Gaussian prior σ of payload / link_inertia θ (∞: none)
        self.prior_mean: dict[str, np.ndarray] = {}    # and its mean (absent: 0, the URDF)
        self.first_prior: dict[str, np.ndarray] = {}   # σ a body's prior starts from when first tightened
        self.flange = np.zeros(10)                      # URDF parameters of the flange link (joint frame)
        self.flange_map = np.eye(10)                    # flange frame → that joint frame (payload θ)
        self.links: list[np.ndarray] = []               # URDF parameters of the other links (joint frames)
        self.dropped: set[tuple[str, tuple, int]] = set()  # (effect, variant, joint or −1) dropped at its prior
        self.nuisance: tuple[Term, ...] = ()
        self.forced: tuple[Term, ...] = ()
        self.t, self.n = train.gap.shape
        self._cache: dict = {}

    @staticmethod
    def _key(term: Term) -> tuple:
        return term.name, term.joints, tuple(sorted(term.variant.items()))

    def design(self, term: Term) -> tuple[np.ndarray, np.ndarray]:
        """(train, held-out) regressor blocks of a term, cached."""
        key = self._key(term)
        if key not in self._cache:
            self._cache[key] = (term.design(self.train), term.design(self.held))
        return self._cache[key]

    def stacked(self, terms: Sequence[Term], part: int = 0) -> np.ndarray:
        """The regressors of ``terms`` and then the ``nuisance`` terms side by side, in θ's order: (T, n, p) of the
        training (``part`` 0) or held-out (1) samples."""
        return np.concatenate([self.design(term)[part] for term in [*terms, *self.nuisance]], axis=2)

    def _normal_blocks(self, one: Term, other: Term) -> np.ndarray:
        """Weighted Gram block Aᵢᵀ W² Aⱼ of two terms' training regressors, cached (hundreds of fits reuse it)."""
        key = ("gram", self._key(one), self._key(other))
        if key not in self._cache:
            a, b = self.design(one)[0], self.design(other)[0]
            w2 = np.square(self.w)
            self._cache[key] = np.einsum("tjp,j,tjq->pq", a, w2, b, optimize=True)
        return self._cache[key]

    def _moment(self, term: Term) -> np.ndarray:
        """Aᵢᵀ W² gap of a term's training regressor, cached."""
        key = ("moment", self._key(term))
        if key not in self._cache:
            self._cache[key] = np.einsum("tjp,j,tj->p", self.design(term)[0], np.square(self.w), self.train.gap,
                                         optimize=True)
        return self._cache[key]

    def fit(self, terms: Sequence[Term]) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """(θ, G⁻¹, train residual, held-out residual); G⁻¹ (p, p), the inverse of the weighted normal matrix with
        the priors, is the bread of ``covariance``. θ and G⁻¹ end with the ``nuisance`` terms' parameters."""
        if not [*terms, *self.nuisance]:
            return np.zeros(0), None, self.train.gap.copy(), self.held.gap.copy()
        theta, gram_scaled, scale = self._solve(terms)
        r_tr = self.train.gap - self.stacked(terms, 0) @ theta
        return theta, np.linalg.pinv(gram_scaled) / np.outer(scale, scale), r_tr, self._held_residual(terms, theta)

    def held_out(self, terms: Sequence[Term]) -> np.ndarray:
        """The held-out residual (T_h, n) N·m of ``fit(terms)``, the same bits, without the train residual and G⁻¹
        that the screens of ``gap.selection`` do not read (they were most of a screening fit's time)."""
        if not [*terms, *self.nuisance]:
            return self.held.gap.copy()
        return self._held_residual(terms, self._solve(terms)[0])

    def _held_residual(self, terms: Sequence[Term], theta: np.ndarray) -> np.ndarray:
        return self.held.gap - self.stacked(terms, 1) @ theta

    def _solve(self, chosen: Sequence[Term]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(θ, scaled normal matrix with the priors, column scale) of the terms and the nuisance terms.

        Bounded weighted least squares on the normal equations: with G = AᵀW²A (+ the priors' 1/σ² on the
        diagonal) = RᵀR and c = AᵀW²b, ‖W(Aθ − b)‖² + ‖θ/σ‖² = ‖Rθ − R⁻ᵀc‖² + const, so BVLS solves a
        p × p problem built from cached blocks instead of a QR of the stacked T·n × p design.
        """
        terms = [*chosen, *self.nuisance]
        gram = np.block([[self._normal_blocks(one, other) for other in terms] for one in terms])
        moment = np.concatenate([self._moment(term) for term in terms])
        lo = np.concatenate([term.bounds(self.priors)[0] for term in terms])
        hi = np.concatenate([term.bounds(self.priors)[1] for term in terms])
        rows = self.t * self.n
        pos = 0
        for term in terms:     # Gaussian priors: rows (Δπ − μ)/σ = 0 (weighted units; μ = 0: the URDF), σ = ∞: no row
            if term.name in self.prior_scale:
                scale = self.prior_scale[term.name]
                mean = self.prior_mean.get(term.name, np.zeros_like(scale))
                if term.name == "payload":
                    scale, mean = scale[term.parameter_index()], mean[term.parameter_index()]
                finite = np.isfinite(scale)
                index = pos + np.flatnonzero(finite)
                gram[index, index] += 1.0 / np.square(scale[finite])
                moment[index] += mean[finite] / np.square(scale[finite])
                rows += len(index)
            pos += term.size
        scale = np.sqrt(np.diag(gram) / rows) + 1e-12                # column scaling for conditioning
        gram_scaled = gram / np.outer(scale, scale)
        try:
            r_mat = np.linalg.cholesky(gram_scaled + 1e-12 * np.trace(gram_scaled) / len(scale)
                                       * np.eye(len(scale))).T
            target = np.linalg.solve(r_mat.T, moment / scale)
            sol = lsq_linear(r_mat, target, bounds=(lo * scale, hi * scale), method="bvls")
        except (np.linalg.LinAlgError, ValueError) as exc:      # which effects failed, for the one-line error
            effects = ", ".join(f"{term.name} on joint(s) {', '.join(str(j + 1) for j in term.joints)}"
                                for term in terms)
            raise np.linalg.LinAlgError(f"the least-squares fit of {effects}: {exc}") from exc
        return sol.x / scale, gram_scaled, scale

    def covariance(self, terms: Sequence[Term], inverse: np.ndarray | None, r_tr: np.ndarray) -> np.ndarray | None:
        """Cov θ (p, p) of a fit (``inverse``: its G⁻¹, ``r_tr``: its train residual (T, n) N·m): the sandwich
        G⁻¹ M G⁻¹ with M the long-run covariance of the scores s_t = A_tᵀ W² r_t (docs/method.md §8.3). The gap's
        misfit is correlated over hundreds of milliseconds; σ² G⁻¹, which takes every sample as independent, gave
        95 % intervals of a payload's mass that held the true mass on 11 of 30 simulated robots."""
        if inverse is None:
            return None
        scores = np.einsum("tjp,j,tj->tp", self.stacked(terms), np.square(self.w), r_tr, optimize=True)
        return inverse @ long_run_covariance(scores) @ inverse

    def bic(self, r_tr: np.ndarray, k: int) -> float:
        mse = np.maximum(np.mean(np.square(r_tr), axis=0), 1e-12)
        return float(self.t * np.sum(np.log(mse)) + k * np.log(self.t * self.n))
