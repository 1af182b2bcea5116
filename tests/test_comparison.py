"""Hellinger distances on grids, across grids and from samples, against the Gaussian closed form."""

import numpy as np
import pytest
from scipy import stats

from newdyn.comparison import (
    distance_matrix,
    hellinger_densities,
    hellinger_gaussians,
    hellinger_grid,
    hellinger_samples,
    hellinger_samples_to_density,
)

# (μ1, σ1, μ2, σ2): identical, close, different widths, very different widths, far apart.
GAUSSIAN_PAIRS = [(0, 1, 0, 1), (0, 1, 0.5, 1), (0, 1, 1, 2), (3, 0.1, 3.2, 5), (0, 1, 20, 1)]


def _on_own_grid(mu, sd, n):
    grid = np.linspace(mu - 10 * sd, mu + 10 * sd, n)
    return grid, stats.norm.pdf(grid, mu, sd)


def test_closed_form_limits():
    assert hellinger_gaussians(1.5, 0.3, 1.5, 0.3) == 0.0
    assert hellinger_gaussians(0, 1, 40, 1) == 1.0
    # Equal widths: H² = 1 − exp(−Δμ²/(8σ²)).
    np.testing.assert_allclose(hellinger_gaussians(0, 2, 3, 2), np.sqrt(1 - np.exp(-9 / 32)), rtol=1e-14)
    np.testing.assert_allclose(
        hellinger_gaussians([0, 0], 1, [0, 3], 1), [0, hellinger_gaussians(0, 1, 3, 1)], atol=1e-15
    )


@pytest.mark.parametrize("mu1, sd1, mu2, sd2", GAUSSIAN_PAIRS)
def test_grid_matches_closed_form(mu1, sd1, mu2, sd2):
    grid = np.linspace(-60, 60, 24001)
    p, q = stats.norm.pdf(grid, mu1, sd1), stats.norm.pdf(grid, mu2, sd2)
    assert abs(hellinger_grid(grid, p, q) - hellinger_gaussians(mu1, sd1, mu2, sd2)) < 1e-3
    # Normalization is internal: a density known up to a factor (e.g. a scaled likelihood) gives the same H.
    assert hellinger_grid(grid, 7 * p, q / p.max()) == pytest.approx(hellinger_grid(grid, p, q), abs=1e-12)


@pytest.mark.parametrize("mu1, sd1, mu2, sd2", GAUSSIAN_PAIRS)
def test_different_grids_match_closed_form(mu1, sd1, mu2, sd2):
    h = hellinger_densities(*_on_own_grid(mu1, sd1, 801), *_on_own_grid(mu2, sd2, 1201))
    assert abs(h - hellinger_gaussians(mu1, sd1, mu2, sd2)) < 1e-3


def test_densities_on_disjoint_or_equal_grids():
    assert hellinger_densities(*_on_own_grid(0, 1, 101), *_on_own_grid(50, 1, 101)) == 1.0
    grid, p = _on_own_grid(2, 0.5, 301)
    q = stats.norm.pdf(grid, 2.3, 0.7)
    assert hellinger_densities(grid, p, grid, q) == pytest.approx(hellinger_grid(grid, p, q), abs=1e-14)


@pytest.mark.parametrize("mu1, sd1, mu2, sd2", GAUSSIAN_PAIRS[1:])
def test_samples_match_closed_form(mu1, sd1, mu2, sd2):
    rng = np.random.default_rng(11)
    a, b = rng.normal(mu1, sd1, 20000), rng.normal(mu2, sd2, 20000)
    assert abs(hellinger_samples(a, b) - hellinger_gaussians(mu1, sd1, mu2, sd2)) < 0.02


def test_samples_of_one_distribution_are_close_and_reproducible():
    def draw(seed):
        rng = np.random.default_rng(seed)
        return hellinger_samples(rng.normal(0, 1, 20000), rng.normal(0, 1, 20000))

    h = draw(5)
    assert h == draw(5)
    # The KDEs' sampling noise leaves a floor of H ≈ 0.014 ± 0.002 at 20000 draws each (40 seeds),
    # so the closed form's 0 is approached from above, not within the 0.02 of distinct distributions.
    assert 0 < h < 0.03


def test_samples_to_density_matches_closed_form():
    rng = np.random.default_rng(2)
    samples = rng.normal(3.1e6, 0.2e6, 20000)
    grid = np.linspace(2.0e6, 4.5e6, 200)  # a calibration grid, coarser than the KDE's
    density = stats.norm.pdf(grid, 3.25e6, 0.15e6)
    expected = hellinger_gaussians(3.1e6, 0.2e6, 3.25e6, 0.15e6)
    assert abs(hellinger_samples_to_density(samples, grid, density) - expected) < 0.02


def test_distance_matrix_is_symmetric_with_zero_diagonal():
    densities = {
        "kT1_up": _on_own_grid(3.25, 0.1, 401),
        "healthy": _on_own_grid(3.0, 0.1, 201),
        "stick_slip": (np.linspace(2, 4.5, 300), np.abs(np.sin(np.linspace(0, 9, 300)))),
    }
    names, matrix = distance_matrix(densities)
    assert names == ["kT1_up", "healthy", "stick_slip"]
    np.testing.assert_array_equal(matrix, matrix.T)
    np.testing.assert_array_equal(np.diag(matrix), 0.0)
    assert matrix[0, 1] == hellinger_densities(*densities["kT1_up"], *densities["healthy"])
    assert abs(matrix[0, 1] - hellinger_gaussians(3.25, 0.1, 3.0, 0.1)) < 1e-3


def test_distance_is_zero_for_identical_and_never_above_one():
    rng = np.random.default_rng(0)
    grid = np.sort(rng.uniform(0, 1, 50))
    for _ in range(200):
        p, q = rng.exponential(size=(2, grid.size)) * (rng.uniform(size=(2, grid.size)) < 0.5)
        p[0] = q[-1] = 1.0  # keep some mass in each
        assert 0.0 <= hellinger_grid(grid, p, q) <= 1.0
        assert 0.0 <= hellinger_densities(grid, p, grid[::2], q[::2]) <= 1.0
        assert hellinger_grid(grid, p, p) == pytest.approx(0.0, abs=1e-7)


def test_invalid_densities_are_refused():
    grid = np.linspace(0, 1, 5)
    with pytest.raises(ValueError, match="non-negative"):
        hellinger_grid(grid, [1, 1, -1, 1, 1], np.ones(5))
    with pytest.raises(ValueError, match="no mass"):
        hellinger_grid(grid, np.zeros(5), np.ones(5))
    with pytest.raises(ValueError, match="increasing"):
        hellinger_densities(grid[::-1], np.ones(5), grid, np.ones(5))


def test_reflected_sample_density_keeps_a_bound_distribution_inside_its_support():
    """Samples of an exponential cut at a bound: with reflection the KDE matches the true density."""
    rng = np.random.default_rng(2)
    samples = 10.0 - rng.exponential(1.0, 20000)  # support (-inf, 10], mode at the bound
    grid = np.linspace(0.0, 10.0, 4001)
    truth = np.exp(grid - 10.0)
    assert hellinger_samples_to_density(samples, grid, truth, bounds=(0.0, 10.0)) < 0.03
    assert hellinger_samples_to_density(samples, grid, truth) > 0.1  # without: mass spills past 10
