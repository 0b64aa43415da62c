"""The payload's prior toward a point mass (gap/admissible.py ``point_mass_moments`` and the Fitter's prior means,
docs/method.md §8.3)."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.gap.admissible import point_mass_moments
from kvark_ros.gap.effects import Priors, Signals, Term
from kvark_ros.gap.fitting import Fitter


def test_point_mass_moments_are_m_times_c_squared_about_the_origin():
    """m = 2 kg at c = (0.1, 0, 0.05) m: ixx = m (cy² + cz²) = 0.005, ixy = −m cx cy = 0, iyy = m (cx² + cz²) = 0.025,
    ixz = −m cx cz = −0.01, iyz = 0, izz = m (cx² + cy²) = 0.02 kg·m²; mass and first moments have mean 0."""
    theta = np.array([2.0, 0.2, 0.0, 0.1, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0])      # its own second moments ignored
    np.testing.assert_allclose(point_mass_moments(theta), [0, 0, 0, 0, 0.005, 0.0, 0.025, -0.01, 0.0, 0.02],
                               atol=1e-15)


def test_a_body_plus_a_point_mass_stays_physically_consistent():
    """A consistent link (1 kg, a 0.1 m cube's inertia about its centre at the origin) with a 3 kg point mass at
    (0.05, 0.02, 0.12) m added: the sum is a physical body, which the prior's mean aims at."""
    link = np.array([1.0, 0.0, 0.0, 0.0, 1 / 600, 0.0, 1 / 600, 0.0, 0.0, 1 / 600])
    mass, com = 3.0, np.array([0.05, 0.02, 0.12])
    point = point_mass_moments(np.concatenate([[mass], mass * com, np.zeros(6)]))
    point[:4] = mass, *(mass * com)
    assert inertia_problem(link + point) is None


@pytest.mark.parametrize("mean", [np.zeros(6), np.array([0.01, -0.002, 0.02, 0.003, 0.0, 0.015])])
def test_the_fitter_pulls_unobserved_parameters_to_the_prior_mean(mean):
    """A payload regressor that sees only mass and first moments (second-moment columns zero): the fit recovers
    those from the gap and puts the second moments at the prior's mean (to 1e-9: exact least squares)."""
    rng = np.random.default_rng(1)
    t, n = 200, 2
    regressor = np.zeros((t, n, 10))
    regressor[:, :, :4] = rng.standard_normal((t, n, 4))
    truth = np.array([1.5, 0.1, -0.05, 0.2])
    gap = regressor[:, :, :4] @ truth
    zeros = np.zeros((t, n))
    signals = Signals(zeros, zeros, zeros, zeros, gap, regressor, np.zeros((t, n, n)), np.zeros((t, n, 0)))
    fitter = Fitter(signals, signals, np.ones(n), Priors())
    fitter.prior_scale["payload"] = np.concatenate([np.full(4, np.inf), np.full(6, 0.1)])
    fitter.prior_mean["payload"] = np.concatenate([np.zeros(4), mean])
    theta = fitter.fit([Term("payload", (0, 1), {})])[0]
    np.testing.assert_allclose(theta[:4], truth, atol=1e-9)
    np.testing.assert_allclose(theta[4:], mean, atol=1e-9)
