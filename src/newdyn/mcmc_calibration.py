"""Calibrate rig parameters against one measurement by MCMC on the simulator (emcee, ArviZ InferenceData).

One parameter (:func:`calibrate_mcmc`, started from its grid posterior, so that the Hellinger distance
between the two checks both) or several jointly, optionally with the noise σ of each channel inferred
too (:func:`calibrate_joint`, started from the best 1-D calibration and a short optimization).  The
priors are the grid calibration's (:mod:`newdyn.calibration`), truncated to the grid ranges.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from . import likelihood, model, posterior, simulation, slots
from .calibration import GridSpec, NormalPrior, explanation_verdict, simulate_points

if TYPE_CHECKING:  # sampling imports arviz (slow); import it where a run needs it
    from .sampling import MCMCSettings

# emcee moves each sampled variable in a coordinate of its own; the prior, the posterior and the
# summaries are always in the variable's own units.  "reciprocal" suits stiffnesses: springs in series
# add as compliances 1/k, so the long ridge of a joint posterior of two shaft stiffnesses seen through
# one torsional mode (1/kT1 + 1/kT3 ≈ constant) is nearly straight in 1/k and sharply curved in k, and
# emcee's ensemble moves only follow straight ridges (measured on kT1+kT3 at 40 dB, 16 walkers × 400
# KDE steps: ESS 2500 in 1/k against 320 in k).  "log" suits scales such as σ (a Jeffreys prior is
# flat in log σ).
_COORDINATES: dict[str, tuple[Callable, Callable, Callable]] = {
    # name: (value -> sampled coordinate, sampled -> value, log |d value / d sampled|)
    "linear": (lambda v: v, lambda x: x, lambda x: np.zeros(np.shape(x))),
    "reciprocal": (np.reciprocal, np.reciprocal, lambda x: -2.0 * np.log(np.abs(x))),
    "log": (np.log, np.exp, lambda x: np.asarray(x, dtype=float)),
}
JOINT_COORDINATE = "reciprocal"  # how calibrate_joint samples the rig parameters (all are stiffnesses)
MIRRORED = True  # rig parameters are sampled mirrored at their grid bounds, alone or jointly (see Variable.mirrored)
SIGMA_PRIOR_RANGE = (1e-4, 1.0)  # σ_c prior support in units of std(y_c): SNR between 80 dB and 0 dB
START_LAPLACE = "Laplace"  # start procedure names recorded in attrs["start"]


@dataclass(frozen=True)
class Variable:
    """One sampled variable: its posterior name, prior support and density, and emcee's coordinate."""

    name: str
    low: float
    high: float
    log_density: Callable[[np.ndarray], np.ndarray]  # prior log density of values inside [low, high]
    draw: Callable[[np.random.Generator, int], np.ndarray]  # prior draws (only those inside the support)
    coordinate: str = "linear"
    # Mirrored: the sampled coordinate runs on one range width past each bound and folds back into the
    # range there (|d fold| = 1, so the folded draws follow the posterior exactly).  A posterior piled
    # against a bound, an exponential tail the bound cuts, becomes a symmetric peak across it that the
    # KDE move samples without proposing into a wall half of the time.  Measured on kT1+kT3 for
    # stick-slip at 40 dB (the corner of both grids; 16 walkers × 400 steps, seeds 1-4): bulk ESS
    # 550-1160 and R-hat 1.012-1.025 mirrored, against 270-650 and 1.024-1.049 not; posteriors inside
    # the ranges are unchanged (bit-identical kT1_up chains).
    mirrored: bool = False

    def sampled(self, value):
        return _COORDINATES[self.coordinate][0](value)

    def fold(self, x):
        if not self.mirrored:
            return x
        low, high = self.sampled_bounds
        return np.where(x < low, 2 * low - x, np.where(x > high, 2 * high - x, x))

    def value(self, x, fold: bool = True):
        """The value at sampled coordinate x; ``fold=False`` continues the coordinate past the bounds
        (for derivatives there: folded, a central difference across a bound would vanish)."""
        return _COORDINATES[self.coordinate][1](self.fold(x) if fold else x)

    def log_prior(self, x: np.ndarray) -> np.ndarray:
        """Prior log density in the sampled coordinate (with the Jacobian), -inf outside the support."""
        with np.errstate(divide="ignore", invalid="ignore"):
            folded = self.fold(x)
            v = _COORDINATES[self.coordinate][1](folded)
            inside = (v >= self.low) & (v <= self.high)
            return np.where(inside, self.log_density(v) + _COORDINATES[self.coordinate][2](folded), -np.inf)

    @property
    def sampled_bounds(self) -> tuple[float, float]:
        """The support in the sampled coordinate (before mirroring)."""
        a, b = self.sampled(self.low), self.sampled(self.high)
        return (float(min(a, b)), float(max(a, b)))

    @property
    def walk_bounds(self) -> tuple[float, float]:
        """Where walkers may go: the sampled support, or three times it when mirrored."""
        low, high = self.sampled_bounds
        return (2 * low - high, 2 * high - low) if self.mirrored else (low, high)


def _parameter_variable(spec: GridSpec, prior: NormalPrior, coordinate: str = "linear") -> Variable:
    """A rig parameter with its Normal prior truncated to the grid range (so MCMC and grid compare)."""
    if coordinate != "linear" and spec.low <= 0:
        raise ValueError(f"{spec.parameter}: {coordinate} coordinates need a positive grid range, got low={spec.low:g}")

    def draw(rng, n):
        x = rng.normal(prior.mean, prior.sd, n)
        return x[(x >= spec.low) & (x <= spec.high)]

    return Variable(spec.parameter, spec.low, spec.high, prior.log_pdf, draw, coordinate, MIRRORED)


def sigma_prior_bounds(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Support (low, high) of each channel's σ prior: [1e-4, 1] × std(y_c) of the data (``SIGMA_PRIOR_RANGE``).

    The noise cannot vary more than the whole measured signal (SNR ≥ 0 dB), and a simulated rig is not
    expected to match to better than 80 dB.  ``data`` is (channel, time).
    """
    scale = np.std(np.asarray(data, dtype=float), axis=-1)
    if not np.all(scale > 0):
        raise ValueError("every channel must vary to bound its noise σ (a constant channel has std 0)")
    return SIGMA_PRIOR_RANGE[0] * scale, SIGMA_PRIOR_RANGE[1] * scale


def sigma_log_prior(sigma, low, high) -> np.ndarray:
    """Normalized log-uniform (Jeffreys) log density of σ on [low, high]: −log σ − log log(high/low)."""
    sigma = np.asarray(sigma, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((sigma >= low) & (sigma <= high), -np.log(sigma) - np.log(np.log(high / low)), -np.inf)


def _sigma_variable(channel: str, low: float, high: float) -> Variable:
    """The noise σ of one channel, Jeffreys prior on [low, high], sampled in log σ (where it is flat)."""
    return Variable(
        f"sigma_{channel}", float(low), float(high), lambda s: sigma_log_prior(s, low, high),
        lambda rng, n: np.exp(rng.uniform(np.log(low), np.log(high), n)), "log",
    )


def _values(variables: Sequence[Variable], x: np.ndarray, fold: bool = True) -> np.ndarray:
    """Rows of sampled coordinates (n, n_variables) -> rows of values."""
    return np.column_stack([v.value(x[:, i], fold) for i, v in enumerate(variables)])


def sampled_rows(variables: Sequence[Variable], values: np.ndarray) -> np.ndarray:
    """Rows of values (n, n_variables) -> rows of sampled coordinates (walker positions)."""
    return np.column_stack([v.sampled(values[:, i]) for i, v in enumerate(variables)])


def _simulator_log_likelihood(data, sigma, parameters, values, sampling, channels, max_step) -> Callable:
    """Log-likelihood of rows of values (n, len(parameters)), one batched simulation per row; with
    ``sigma`` None each row also holds the σ of every channel after its parameters."""
    n = len(parameters)

    def log_likelihood(rows: np.ndarray) -> np.ndarray:
        models = simulate_points(values, parameters, rows[:, :n], sampling, channels, max_step)
        ll = likelihood.log_likelihood(data, models, sigma if sigma is not None else rows[:, n:])
        return np.where(np.isnan(ll), -np.inf, ll)  # a failed simulation has zero likelihood (emcee stops on NaN)

    return log_likelihood


def sample_posterior(
    variables: Sequence[Variable],
    log_likelihood: Callable[[np.ndarray], np.ndarray],
    initial: np.ndarray,
    settings: MCMCSettings,
    rng: np.random.Generator,
    observed: Mapping | None = None,
    attrs: Mapping[str, object] | None = None,
    move: tuple | None = None,
):
    """emcee (:func:`sampling.run`) over ``variables`` from ``initial`` (n_walkers, n_variables), the
    walkers' positions in the sampled coordinates (``move``: as :func:`sampling.run`'s, else ``settings.move``).

    The walkers move in each variable's coordinate; the posterior group holds values, and the
    convergence diagnostics are those of the values.  ``rng`` draws the prior group.
    """
    from . import sampling as mcmc

    names = [v.name for v in variables]
    prior_samples = {v.name: v.draw(rng, 4 * settings.n_steps) for v in variables}
    return mcmc.run(
        lambda x: log_likelihood(_values(variables, x)),
        lambda x: np.sum([v.log_prior(x[:, i]) for i, v in enumerate(variables)], axis=0),
        names, initial, settings, to_values=lambda x: _values(variables, x),
        prior_samples=prior_samples, observed=observed,
        attrs={**(attrs or {}), "coordinates": {v.name: v.coordinate + (", mirrored" if v.mirrored else "") for v in variables}},
        move=move,
    )


def _observed(data: np.ndarray, sampling: model.Sampling, channels: Sequence[str]) -> dict:
    return {"y": xr.DataArray(data, dims=("channel", "time"), coords={"channel": list(channels), "time": sampling.times})}


def calibrate_mcmc(
    data: np.ndarray,
    sigma: np.ndarray,
    spec: GridSpec,
    prior: NormalPrior,
    grid_posterior: likelihood.GridPosterior,
    values: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    settings: MCMCSettings,
    max_step: float = simulation.DEFAULT_MAX_STEP,
    attrs: Mapping[str, object] | None = None,
    proposal: str = "move",
):
    """MCMC posterior (emcee, ArviZ InferenceData) of ``spec.parameter`` on the real simulator.

    The prior is the Normal prior truncated to the grid range, so MCMC and the grid target the same
    posterior and their Hellinger distance is a check of both.  Walkers start from draws of the grid
    posterior: the chains start stationary and need little burn-in.  Mirrored at the grid bounds: for a
    posterior piled against kT1's bound (stick-slip, cubic coupling at 40 and 20 dB; 16 walkers × 150
    steps, seeds 1-2) bulk ESS 716-768 and R-hat 1.012-1.026, against 157-617 and 1.017-1.082 not
    mirrored; chains inside the range are bit-identical.
    """
    rng = np.random.default_rng(settings.seed)
    initial = np.interp(rng.uniform(size=settings.n_walkers), grid_posterior.cdf, grid_posterior.grid)[:, None]
    if proposal not in PROPOSALS:
        raise ValueError(f"proposal must be one of {', '.join(PROPOSALS)}, got {proposal!r}")
    return sample_posterior(  # linear coordinate: the positions are the values, folded at the bounds
        [_parameter_variable(spec, prior)],
        _simulator_log_likelihood(data, sigma, [spec.parameter], values, sampling, channels, max_step),
        initial, settings, rng, _observed(data, sampling, channels), attrs,
        move=grid_move(grid_posterior, spec.low, spec.high) if proposal == "grid" else None,
    )


PROPOSALS = ("move", "grid")  # a one-parameter run's proposal: emcee's ensemble move (settings.move), or the grid's
GRID_DEFENSIVE = 0.05  # the share of a grid proposal's draws that are uniform over the grid range


def grid_move(grid_posterior: likelihood.GridPosterior, low: float, high: float):
    """An independence proposal from the measurement's grid posterior (:func:`newdyn.sampling.independence_move`), the
    study's own surrogate of the one-parameter posterior, so that each simulation gives nearly an independent draw
    (emcee's KDE move, which learns the posterior from the other walkers, decorrelates in about two): walkers propose
    from the grid's cdf, linear between grid points (a density constant on each grid cell), mixed with
    ``GRID_DEFENSIVE`` uniform over [low, high].  The uniform share keeps the proposal's density above zero wherever the
    posterior has mass, cells the grid gave none included, so the ratio of posterior to proposal stays bounded and the
    chain is uniformly ergodic even where the grid misses (Hesterberg's defensive mixture).  The simulator's
    likelihood decides every move: the draws follow the posterior on the simulator, not the grid's."""
    from .sampling import independence_move

    grid = grid_posterior.grid
    cdf = grid_posterior.cdf / grid_posterior.cdf[-1]
    with np.errstate(divide="ignore"):
        cell_density = np.diff(cdf) / np.diff(grid)
    share = GRID_DEFENSIVE

    def draw(random, n):
        u, uniform = random.uniform(size=n), random.uniform(size=n) < share
        x = np.where(uniform, low + u * (high - low), np.interp(u, cdf, grid))
        return x[:, None]

    def log_density(x):
        x = x[:, 0]
        cell = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, grid.size - 2)
        inside = (x >= low) & (x <= high)
        with np.errstate(divide="ignore"):
            return np.where(inside, np.log((1 - share) * cell_density[cell] + share / (high - low)), -np.inf)

    return independence_move(draw, log_density), f"independence MHMove(grid posterior, {share:g} uniform)"


def calibrate_joint(
    data: np.ndarray,
    sigma: np.ndarray | None,
    specs: Sequence[GridSpec],
    priors: Sequence[NormalPrior],
    grid_posteriors: Sequence[likelihood.GridPosterior],
    values: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    settings: MCMCSettings,
    infer_sigma: bool = False,
    max_step: float = simulation.DEFAULT_MAX_STEP,
    attrs: Mapping[str, object] | None = None,
):
    """Joint posterior (ArviZ InferenceData) of several parameters on the real simulator, with the noise σ of each
    channel known (``sigma``) or inferred (``infer_sigma``, ``sigma`` None): around the Laplace approximation of the
    start below by quadrature or importance sampling where :mod:`newdyn.posterior` verifies that, else by emcee.

    ``specs``, ``priors`` and ``grid_posteriors`` are per parameter, in one order: each prior is the
    Normal prior truncated to the grid range, as in :func:`calibrate_mcmc`, and each grid posterior is
    that parameter's 1-D calibration on the same data (the others at ``values``); they only choose the
    start.  The posterior group holds one variable per parameter and, when σ is inferred, one
    ``sigma_<channel>`` per channel.

    Inferred σ: σ_c has a log-uniform (Jeffreys, p(σ) ∝ 1/σ) prior on [1e-4, 1] × std(y_c) (see
    :func:`sigma_prior_bounds`), independent across channels, and is sampled as log σ_c; the Gaussian
    likelihood keeps its −N log σ_c normalization, so for a fixed model σ_c² is Inverse-Gamma(N/2, RSS_c/2).
    The parameters are sampled as 1/value (``JOINT_COORDINATE``; see ``_COORDINATES``), mirrored at
    their grid bounds (``MIRRORED``; see ``Variable``); their prior and posterior are in their
    own units.

    Start (the joint posterior of stiffnesses seen through one mode is a long ridge that draws of
    the 1-D, conditional, grid posteriors miss): the 1-D calibration with the highest maximum
    log-likelihood at its MAP, the other parameters at ``values``; then a bounded least-squares
    optimization to the joint MAP (scipy ``least_squares``, central-difference Jacobians from one
    batched simulation; with σ inferred, σ_c is profiled out as the rms residual and the fit repeated
    once with it); then walkers drawn from the Laplace approximation there: Normal with covariance
    (JᵀJ)⁻¹ for parameters inside their range, for those the optimum holds at a bound the exponential
    tail of length 1/|∂ log p| the bound cuts (mirrored: a Laplace peak across the bound), and log σ_c ~
    N(log σ̂_c, 1/(2N)).  ``attrs["start"]`` records it.  Measured on kT1_up at 40 dB (default record,
    16 walkers × 400 KDE steps): this start and one from a ball of 1-D posterior sds at the best 1-D
    calibration both reach ESS ≈ 2000-2500 in 1/k, where sampling k itself reaches 140-380 from either.

    Attributes added: ``jointly`` ("+"-joined names), ``parameters``, ``coordinates``, ``start``,
    ``support`` (each variable's prior range), ``sigma_prior``, ``best_rss`` (per-channel residual
    sum of squares at the highest-likelihood draw, one extra simulation), ``posterior_correlation``.
    """
    if len(specs) == 0 or not len(specs) == len(priors) == len(grid_posteriors):
        raise ValueError("give at least one parameter, with one spec, prior and grid posterior each")
    if infer_sigma == (sigma is not None):
        raise ValueError("pass the known sigma, or sigma=None with infer_sigma=True (not both, not neither)")
    data = np.asarray(data, dtype=float)
    parameters = [spec.parameter for spec in specs]
    variables = [_parameter_variable(spec, prior, JOINT_COORDINATE) for spec, prior in zip(specs, priors)]
    sigma_bounds = sigma_prior_bounds(data) if infer_sigma else None
    if infer_sigma:
        variables += [_sigma_variable(c, low, high) for c, low, high in zip(channels, *sigma_bounds)]
    _check_walkers(settings, [v.name for v in variables])

    rng = np.random.default_rng(settings.seed)
    initial, start, (mean, covariance) = _joint_start(
        data, sigma, variables, priors, grid_posteriors, values, sampling, channels, max_step, settings.n_walkers, rng
    )
    log_likelihood = _simulator_log_likelihood(data, sigma, parameters, values, sampling, channels, max_step)
    described = {
        **(attrs or {}),
        "jointly": "+".join(v.name for v in variables),
        "parameters": parameters,
        "infer_sigma": bool(infer_sigma),
        "start": start,
        "support": {v.name: [v.low, v.high] for v in variables},
        "sigma_prior": (
            {"kind": "log-uniform (Jeffreys) on [1e-4, 1] x std(y_c), sampled in log sigma",
             "bounds": {f"sigma_{c}": [lo, hi] for c, lo, hi in zip(channels, *sigma_bounds)}}
            if infer_sigma else "known"
        ),
    }
    # Around the Laplace approximation first, in the sampled coordinates (1/k, where two stiffnesses seen through one
    # mode trade off along a nearly straight ridge) but not mirrored: the support's bounds are where the posterior ends.
    plain = [replace(v, mirrored=False) for v in variables]
    found = posterior.sample(
        lambda x: log_likelihood(_values(plain, x)),
        lambda x: np.sum([v.log_prior(x[:, i]) for i, v in enumerate(plain)], axis=0),
        [v.name for v in variables], mean, covariance,
        posterior.PosteriorSettings(seed=settings.seed, ess_min=settings.ess_min), observed=_observed(data, sampling, channels),
        attrs={**described, "coordinates": {v.name: v.coordinate for v in variables}}, to_values=lambda x: _values(plain, x),
    )
    if found.attrs["converged"]:
        idata = found
    else:
        idata = sample_posterior(variables, log_likelihood, initial, settings, rng, _observed(data, sampling, channels),
                                 {**described, "why": f"{found.attrs['method']} unverified ({found.attrs['reason']})"})
        idata.attrs["method"] = "mcmc"
    draws = np.column_stack([idata.posterior[v.name].values.ravel() for v in variables])
    best = draws[np.argmax(idata.sample_stats["log_likelihood"].values.ravel())]
    residual = data - simulate_points(values, parameters, best[None, : len(parameters)], sampling, channels, max_step)[0]
    idata.attrs.update(
        best_rss=json.dumps(np.sum(residual**2, axis=-1).tolist()),
        posterior_correlation=json.dumps(
            {"variables": [v.name for v in variables], "matrix": np.atleast_2d(np.corrcoef(draws.T)).tolist()}
        ),
    )
    return idata


def _check_walkers(settings: MCMCSettings, names: Sequence[str]) -> None:
    """emcee's ensemble moves need n_walkers ≥ 2·ndim; the KDE move a nonsingular KDE of half the ensemble."""
    ndim = len(names)
    need, why = 2 * ndim, "emcee needs n_walkers >= 2 * ndim"
    if settings.move == "kde":  # half the ensemble must span the space, else its KDE is singular
        need, why = 2 * ndim + 2, why + ", and the KDE move n_walkers // 2 > ndim"
    if settings.n_walkers < need:
        raise ValueError(
            f"n_walkers must be at least {need} for {ndim} sampled variables ({', '.join(names)}): {why}; "
            f"got {settings.n_walkers}"
        )


def _joint_start(data, sigma, variables, priors, grid_posteriors, values, sampling, channels, max_step, n_walkers, rng):
    """Initial walker positions (n_walkers, n_variables) in the sampled coordinates, and the record of
    how they were found (the procedure is described in :func:`calibrate_joint`)."""
    from scipy import optimize

    n = len(priors)
    params, sigmas = variables[:n], variables[n:]
    names = [v.name for v in params]
    n_runs = 0

    def simulate(rows):
        nonlocal n_runs
        n_runs += len(rows)
        return simulate_points(values, names, rows, sampling, channels, max_step)

    def rms(rows):  # per-channel rms residual of each row's model: σ's profile MLE
        return np.sqrt(np.mean((data - simulate(rows)) ** 2, axis=-1))

    low, high = np.array([v.sampled_bounds for v in params]).T
    inner = 1e-9 * (high - low)  # the start stays strictly inside, also after 1/(1/x)
    best = int(np.argmax([g.log_likelihood.max() for g in grid_posteriors]))
    k0 = np.array([slots.complete(values)[name] for name in names])
    k0[best] = grid_posteriors[best].map
    k0 = np.clip(k0, [v.low for v in params], [v.high for v in params])
    x0 = np.clip(sampled_rows(params, k0[None])[0], low + inner, high - inner)
    k_sd = np.array([g.sd for g in grid_posteriors])
    scale = np.abs(sampled_rows(params, (k0 + k_sd)[None])[0] - x0)  # 1-D posterior sds in sampled units
    scale = np.where(scale > 0, scale, np.abs(x0) * 1e-6 + 1e-12)
    mean, sd = np.array([p.mean for p in priors]), np.array([p.sd for p in priors])

    def residuals(x, weights):  # rows (m, n) -> (m, N·C + n): standardized misfit and prior terms
        k = _values(params, x, fold=False)  # the optimizer stays in bounds; its differences may not
        misfit = ((data - simulate(k)) / weights[:, None]).reshape(len(x), -1)
        return np.concatenate([misfit, (k - mean) / sd], axis=1)

    def fit(x_start, weights):
        def jacobian(x):
            h = 0.5 * scale
            rows = residuals(np.concatenate([x + np.diag(h), x - np.diag(h)]), weights)
            return ((rows[:n] - rows[n:]) / (2 * h[:, None])).T

        return optimize.least_squares(
            lambda x: residuals(x[None], weights)[0], x_start, jac=jacobian, bounds=(low, high),
            x_scale=scale, method="trf", max_nfev=50,
        )

    record = {"procedure": START_LAPLACE, "from": names[best], "initial": dict(zip(names, k0.tolist()))}
    sigma_range = np.array([[v.low, v.high] for v in sigmas]).T if sigmas else None
    weights = sigma if sigma is not None else np.clip(rms(k0[None])[0], *sigma_range)
    try:
        result = fit(x0, weights)
        if sigma is None:  # profile σ out: refit with the σ the first fit leaves, then take its own
            weights = np.clip(rms(_values(params, result.x[None]))[0], *sigma_range)
            result = fit(result.x, weights)
        x_star, jac, grad, active = result.x, result.jac, result.grad, result.active_mask
        misfit = result.fun[: data.size].reshape(data.shape) * weights[:, None]
        weights = np.sqrt(np.mean(misfit**2, axis=-1))  # the σ this optimum leaves (known σ: unused)
        record["optimizer"] = {"nfev": int(result.nfev), "njev": int(result.njev), "status": int(result.status),
                               "cost": float(result.cost)}
    except ValueError as exc:  # e.g. non-finite residuals (a failed simulation): start around k0
        record["optimizer"] = {"failed": str(exc)}
        x_star, jac, grad, active = x0, np.diag(1 / scale), np.zeros(n), np.zeros(n, dtype=int)

    # Walkers: the Laplace approximation at the optimum; at an active bound, the exponential tail it cuts.
    hessian = jac.T @ jac
    x = np.empty((n_walkers, n))
    laplace = np.zeros((n, n))  # its covariance, each bound parameter's tail length squared on the diagonal
    free = active == 0
    if free.any():
        cov = np.linalg.pinv(hessian[np.ix_(free, free)])
        laplace[np.ix_(free, free)] = cov
        x[:, free] = draw_inside(lambda m: rng.multivariate_normal(x_star[free], cov, m), low[free], high[free], n_walkers)
    for i in np.flatnonzero(~free):
        length = 1 / max(abs(grad[i]), np.sqrt(hessian[i, i]), 1 / (high[i] - low[i]))
        laplace[i, i] = length**2
        bound, sign = (low[i], 1.0) if active[i] < 0 else (high[i], -1.0)
        walk_low, walk_high = params[i].walk_bounds
        draw = _bound_tail(rng, bound, sign, length, params[i].mirrored)
        x[:, i] = draw_inside(draw, np.array([walk_low]), np.array([walk_high]), n_walkers)[:, 0]
    record.update(
        n_simulations=n_runs,
        map=dict(zip(names, _values(params, x_star[None])[0].tolist())),
        at_bound=[name for name, a in zip(names, active) if a],
    )
    mean = x_star
    if sigmas:  # sampled as log σ
        sigma_hat = np.clip(weights, *sigma_range)
        spread = 1 / np.sqrt(2 * data.shape[-1])  # sd of log σ̂ from N samples
        log_low, log_high = np.array([v.sampled_bounds for v in sigmas]).T
        log_sigma = draw_inside(lambda m: rng.normal(np.log(sigma_hat), spread, (m, len(sigmas))), log_low, log_high, n_walkers)
        x = np.column_stack([x, log_sigma])
        record["sigma"] = dict(zip([v.name for v in sigmas], sigma_hat.tolist()))
        mean = np.concatenate([x_star, np.log(sigma_hat)])
        laplace = np.block([[laplace, np.zeros((n, len(sigmas)))], [np.zeros((len(sigmas), n)), spread**2 * np.eye(len(sigmas))]])
    return x, record, (mean, laplace)


def _bound_tail(rng: np.random.Generator, bound: float, sign: float, length: float, mirrored: bool) -> Callable[[int], np.ndarray]:
    """Draws (m, 1) near a bound that a Laplace approximation's optimum holds: the exponential tail of
    ``length`` that the bound cuts, on its ``sign`` side, or with its mirror image (a Laplace peak across it)."""

    def draw(m):
        step = rng.laplace(0.0, length, m) if mirrored else sign * rng.exponential(length, m)
        return (bound + step)[:, None]

    return draw


def draw_inside(draw: Callable[[int], np.ndarray], low: np.ndarray, high: np.ndarray, n: int) -> np.ndarray:
    """n rows of ``draw`` strictly inside (low, high): rows outside are redrawn, a few times, then clipped."""
    margin = 1e-9 * (high - low)
    rows = draw(n)
    for _ in range(20):
        outside = np.any((rows <= low) | (rows >= high), axis=1)
        if not outside.any():
            break
        rows[outside] = draw(int(outside.sum()))
    return np.clip(rows, low + margin, high - margin)


def _best_draw(idata) -> tuple:
    """Index (chain, draw) of the highest log posterior."""
    return np.unravel_index(np.argmax(idata.sample_stats["lp"].values), idata.sample_stats["lp"].shape)


def draws_summary(draws: np.ndarray, map_value: float, prior_sd: float) -> dict:
    """MAP, mean, sd, 94% HDI and posterior-to-prior sd ratio of one variable's draws."""
    import arviz as az

    low, high = az.hdi(draws, hdi_prob=likelihood.HDI_PROB)
    sd = float(draws.std(ddof=1))
    return {"map": float(map_value), "mean": float(draws.mean()), "sd": sd, "hdi_low": float(low),
            "hdi_high": float(high), "sd_ratio": sd / prior_sd}


def mcmc_summary(
    idata, parameter: str, prior: NormalPrior, grid_posterior: likelihood.GridPosterior, sigma: np.ndarray, chi2_max: float
) -> dict:
    """The summary row of an MCMC calibration, with its agreement with the grid posterior."""
    from .comparison import hellinger_samples_to_density

    draws = idata.posterior[parameter].values.ravel()
    n_samples = idata.observed_data["y"].shape[-1]
    best_ll = float(idata.sample_stats["log_likelihood"].values.max())
    chi2_red = likelihood.chi2_from_log_likelihood(best_ll, sigma, n_samples) / (sigma.size * n_samples - 1)
    converged = bool(idata.attrs["converged"])
    n_peaks = grid_posterior.n_peaks()
    return {
        **draws_summary(draws, idata.posterior[parameter].values[_best_draw(idata)], prior.sd),
        "n_peaks": n_peaks,
        "chi2_red": chi2_red,
        "rhat": float(idata.attrs["rhat"]),
        "ess_bulk": float(idata.attrs["ess_bulk"]),
        "converged": converged,
        "verdict": explanation_verdict(chi2_red, chi2_max, grid_posterior.consistent(), converged),
        "hellinger_to_grid": hellinger_samples_to_density(
            draws, grid_posterior.grid, grid_posterior.density, bounds=(grid_posterior.grid[0], grid_posterior.grid[-1])
        ),
    }


def joint_summary(idata, priors: Mapping[str, NormalPrior], chi2_max: float, sigma: np.ndarray | None = None) -> list[dict]:
    """Summary rows of a :func:`calibrate_joint` result, one per sampled variable (parameters, then σs).

    Keys as :func:`mcmc_summary`'s plus ``parameter`` (the variable) and ``jointly`` (all of them,
    "+"-joined), with these joint meanings:

    - ``chi2_red``: Σ_c RSS_c/σ_c² / (N·C − n_variables) at the highest-likelihood draw, against
      ``sigma`` when given (the known noise), else against the posterior-mean σ_c.  Inferring σ fits
      it to the residuals, so then χ² ≈ 1 by construction and cannot tell misfit from noise.
    - ``n_peaks``: modes of the variable's marginal posterior, a reflected KDE of its draws
      (comparison.sample_density) counted as :meth:`likelihood.GridPosterior.n_peaks` counts peaks
      (prominence ≥ 5 % of the highest).
    - ``rhat``, ``ess_bulk``: of this variable (MCMC; importance sampling: NaN and its weights' effective sample
      size; quadrature: NaN); ``converged``: of the whole run (all variables), verified for the others.
    - ``verdict``: one for the joint calibration, from χ², convergence and every variable's marginal
      (one peak, inside its support).
    - ``sd_ratio``: to the prior sd (NaN for σ); ``hellinger_to_grid``: NaN, as the 1-D grid posterior
      is conditional on the other parameters at their model values, not the joint marginal.
    """
    import arviz as az

    names = list(idata.posterior.data_vars)
    support = json.loads(idata.attrs["support"])
    rss = np.array(json.loads(idata.attrs["best_rss"]))
    n_channels, n_samples = idata.observed_data["y"].shape
    if sigma is None:
        channels = [str(c) for c in idata.observed_data["channel"].values]
        if not all(f"sigma_{c}" in names for c in channels):
            raise ValueError("σ was not inferred: pass the known sigma")
        sigma = np.array([float(idata.posterior[f"sigma_{c}"].mean()) for c in channels])
    chi2_red = float(np.sum(rss / np.asarray(sigma, dtype=float) ** 2) / (n_channels * n_samples - len(names)))
    if idata.attrs.get("method") == "mcmc":
        rhat, ess = az.rhat(idata.posterior, method="rank"), az.ess(idata.posterior, method="bulk")
    else:  # a verified quadrature or importance-sampled answer has no chains: its weights' effective size, if any
        rhat = {name: float("nan") for name in names}
        ess = {name: float(idata.attrs.get("ess_bulk", "nan")) for name in names}
    converged = bool(idata.attrs["converged"])
    best = _best_draw(idata)
    marginals = {name: _marginal(idata.posterior[name].values.ravel(), tuple(support[name])) for name in names}
    n_peaks = {name: marginal.n_peaks() for name, marginal in marginals.items()}
    verdict = explanation_verdict(chi2_red, chi2_max, all(m.consistent() for m in marginals.values()), converged)
    return [
        {
            "parameter": name,
            **draws_summary(idata.posterior[name].values.ravel(), idata.posterior[name].values[best],
                             priors[name].sd if name in priors else np.nan),
            "n_peaks": n_peaks[name],
            "chi2_red": chi2_red,
            "rhat": float(rhat[name]),
            "ess_bulk": float(ess[name]),
            "converged": converged,
            "verdict": verdict,
            "hellinger_to_grid": float("nan"),
            "jointly": "+".join(names),
        }
        for name in names
    ]


def _marginal(draws: np.ndarray, bounds: tuple[float, float]) -> likelihood.GridPosterior:
    """The marginal posterior of one variable on its support, from a reflected KDE of its draws, so
    that its peaks are counted as a grid calibration's are."""
    from .comparison import sample_density

    grid, density = sample_density(draws, bounds)
    with np.errstate(divide="ignore"):
        return likelihood.grid_posterior(grid, np.log(density), 0.0)
