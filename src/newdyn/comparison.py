"""Similarity of posteriors: Hellinger distance (the paper's Step 3).

H(p, q)² = 1 − ∫ √(p q) dφ, between 0 for identical distributions and 1 for distributions with
disjoint supports.  Posteriors come as densities on grids (from :func:`newdyn.likelihood.grid_posterior`),
as samples (e.g. from MCMC), or as Gaussians in closed form; every function here returns H, not H².
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy import stats
from scipy.integrate import trapezoid

# Points of the grid on which a sample set's kernel density estimate is evaluated: for 20000 Gaussian
# draws that is ~7 points per bandwidth, and H moves by < 1e-5 when going to 4096 points.
KDE_GRID_POINTS = 512
# The KDE grid extends this many bandwidths past the extreme samples, where a kernel has decayed to e^-8.
KDE_GRID_MARGIN_BANDWIDTHS = 4.0


def _hellinger_from_overlap(bhattacharyya: float) -> float:
    # Quadrature and rounding can push the overlap a hair outside [0, 1].
    return float(np.sqrt(np.clip(1.0 - bhattacharyya, 0.0, 1.0)))


def _normalized(grid, density) -> tuple[np.ndarray, np.ndarray]:
    """Validated (grid, density) with the density rescaled to integrate to 1 by the trapezoidal rule."""
    grid, density = np.asarray(grid, dtype=float), np.asarray(density, dtype=float)
    if grid.ndim != 1 or grid.size < 2 or np.any(np.diff(grid) <= 0):
        raise ValueError("grid must be a 1-D, strictly increasing array of at least 2 points")
    if density.shape != grid.shape or not np.all(np.isfinite(density)) or np.any(density < 0):
        raise ValueError(f"density must be {grid.size} finite non-negative values on the grid")
    mass = trapezoid(density, grid)
    if mass <= 0:
        raise ValueError("density has no mass on its grid")
    return grid, density / mass


def hellinger_gaussians(mu1, sd1, mu2, sd2):
    """Closed-form Hellinger distance between N(mu1, sd1²) and N(mu2, sd2²); broadcasts over arrays."""
    mu1, sd1, mu2, sd2 = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (mu1, sd1, mu2, sd2)))
    variance_sum = sd1**2 + sd2**2
    overlap = np.sqrt(2 * sd1 * sd2 / variance_sum) * np.exp(-((mu1 - mu2) ** 2) / (4 * variance_sum))
    h = np.sqrt(np.clip(1.0 - overlap, 0.0, 1.0))
    return float(h) if h.ndim == 0 else h


def hellinger_grid(grid, p, q) -> float:
    """Hellinger distance between densities ``p`` and ``q`` given on the same ``grid``.

    Each is renormalized on the grid first, so unnormalized densities (e.g. a scaled likelihood) are fine.
    """
    grid, p = _normalized(grid, p)
    _, q = _normalized(grid, q)
    return _hellinger_from_overlap(trapezoid(np.sqrt(p * q), grid))


def hellinger_densities(grid_p, p, grid_q, q) -> float:
    """Hellinger distance between density ``p`` on ``grid_p`` and ``q`` on ``grid_q`` (grids may differ).

    Each density is normalized on its own grid and taken as zero outside it.  The overlap ∫ √(p q) is
    integrated over the union of both grids' points inside the common range, with each density linearly
    interpolated there; outside the common range the product is zero.
    """
    grid_p, p = _normalized(grid_p, p)
    grid_q, q = _normalized(grid_q, q)
    low, high = max(grid_p[0], grid_q[0]), min(grid_p[-1], grid_q[-1])
    if low >= high:
        return 1.0
    union = np.union1d(grid_p, grid_q)
    common = union[(union >= low) & (union <= high)]
    overlap = trapezoid(np.sqrt(np.interp(common, grid_p, p) * np.interp(common, grid_q, q)), common)
    return _hellinger_from_overlap(overlap)


def _kde(samples) -> stats.gaussian_kde:
    samples = np.asarray(samples, dtype=float)
    if samples.ndim != 1 or samples.size < 2 or not np.all(np.isfinite(samples)):
        raise ValueError("samples must be a 1-D array of at least 2 finite values")
    return stats.gaussian_kde(samples)  # Scott's rule bandwidth


def _kde_grid(kde: stats.gaussian_kde) -> np.ndarray:
    """A grid resolving ``kde`` over its samples' range plus a margin where the kernels have decayed."""
    bandwidth = np.sqrt(kde.covariance[0, 0])
    margin = KDE_GRID_MARGIN_BANDWIDTHS * bandwidth
    return np.linspace(kde.dataset.min() - margin, kde.dataset.max() + margin, KDE_GRID_POINTS)


def hellinger_samples(a, b, grid=None) -> float:
    """Hellinger distance between the distributions of 1-D samples ``a`` and ``b``, via Gaussian KDEs.

    Both KDEs are evaluated on ``grid`` or, by default, on the union of a fine grid for each sample set
    (its range ± 4 bandwidths), so that one set much narrower than the other is still resolved.  The KDE
    widens each distribution slightly (Scott's rule adds ≈ n^(-2/5) to the relative variance) and
    finite samples add noise of order 0.01 to H at 20000 draws each: small distances are not exact.
    """
    kde_a, kde_b = _kde(a), _kde(b)
    if grid is None:
        grid = np.union1d(_kde_grid(kde_a), _kde_grid(kde_b))
    grid = np.asarray(grid, dtype=float)
    return hellinger_grid(grid, kde_a(grid), kde_b(grid))


def sample_density(samples, bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(grid, density) of 1-D ``samples`` by a Gaussian KDE.

    With ``bounds`` (the support, e.g. a truncated prior's) the KDE is reflected at them, so that
    samples piled against a bound do not spill mass beyond it.
    """
    kde = _kde(samples)
    grid = _kde_grid(kde)
    if bounds is None:
        return grid, kde(grid)
    low, high = bounds
    grid = np.unique(np.clip(grid, low, high))
    return grid, kde(grid) + kde(2 * low - grid) + kde(2 * high - grid)


def hellinger_samples_to_density(samples, grid, density, bounds: tuple[float, float] | None = None) -> float:
    """Hellinger distance between the distribution of 1-D ``samples`` (via :func:`sample_density`) and
    ``density`` on ``grid``.  The KDE's mass outside ``grid`` counts as disagreement; pass the support
    ``bounds`` when the samples pile against a hard bound."""
    return hellinger_densities(*sample_density(samples, bounds), grid, density)


def distance_matrix(densities: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> tuple[list[str], np.ndarray]:
    """Pairwise Hellinger distances between named (grid, density) pairs, grids possibly different.

    Returns the names in the mapping's order and the symmetric matrix with zeros on its diagonal.
    """
    names = list(densities)
    matrix = np.zeros((len(names), len(names)))
    for i, first in enumerate(names):
        for j in range(i + 1, len(names)):
            matrix[i, j] = matrix[j, i] = hellinger_densities(*densities[first], *densities[names[j]])
    return names, matrix


def signature_matrices(posteriors: Mapping[tuple[str, str, float, int], tuple[np.ndarray, np.ndarray]]):
    """Hellinger distances between every pair of scenarios' posteriors of the same parameter, SNR and seed.

    ``posteriors`` maps (scenario, parameter, snr_db, seed) to a posterior (grid, density).  Each
    scenario's posterior is the predicted signature of its change (the paper's Step 1); row ``scenario``,
    column ``reference`` of the result is the distance of its posterior to the reference's (Step 3).
    Returns an :class:`xarray.DataArray` with dims (parameter, snr_db, seed, scenario, reference), NaN
    where a combination was not calibrated.
    """
    import xarray as xr

    posteriors = {(str(s), str(p), float(snr), int(seed)): v for (s, p, snr, seed), v in posteriors.items()}
    keys = list(posteriors)
    scenarios = list(dict.fromkeys(k[0] for k in keys))
    coords = {
        "parameter": list(dict.fromkeys(k[1] for k in keys)),
        "snr_db": sorted({float(k[2]) for k in keys}, reverse=True),
        "seed": sorted({int(k[3]) for k in keys}),
        "scenario": scenarios,
        "reference": scenarios,
    }
    distances = xr.DataArray(np.full([len(c) for c in coords.values()], np.nan), coords=coords, dims=list(coords))
    for parameter in coords["parameter"]:
        for snr in coords["snr_db"]:
            for seed in coords["seed"]:
                present = {s: posteriors[(s, parameter, snr, seed)] for s in scenarios if (s, parameter, snr, seed) in posteriors}
                names, matrix = distance_matrix(present)
                distances.loc[{"parameter": parameter, "snr_db": snr, "seed": seed, "scenario": names, "reference": names}] = matrix
    distances.attrs.update(long_name="Hellinger distance between posteriors", units="1")
    return distances
