"""Posteriors by importance sampling from a fit's Laplace approximation, verified by Pareto smoothing.

Where a posterior is close to Gaussian, as a fitted effect's usually is at the noise levels newdyn sees, draws of
a heavy-tailed Student-t around the Laplace approximation (the least-squares optimum and its Gauss–Newton
covariance), weighted by posterior over proposal, give the posterior for a fraction of an MCMC run's simulations,
and all of them in large batches.  Pareto-smoothed importance sampling (:func:`arviz.psislw`, Vehtari et al. 2024)
smooths the weights, and its shape estimate k̂ says whether the estimate can be trusted: at k̂ ≤ 0.7 the proposal
covers the posterior's bulk and tails.  Draws are added a batch at a time until the smoothed weights' effective
sample size reaches its target; when k̂ says the proposal misses the posterior, or the target is not reached, the
result is marked unverified and the caller samples by MCMC instead.

The result is an :class:`arviz.InferenceData` shaped like :func:`newdyn.sampling.run`'s: a ``posterior`` of one chain
of equally weighted draws (systematic resampling of the weighted ones), ``sample_stats`` with their ``lp`` and
``log_likelihood``, an ``importance`` group with every proposed draw inside the prior's support, its smoothed log
weight and log-likelihood, and attributes: ``method``, ``converged`` (1 when verified, as netCDF has no booleans),
``pareto_k``, ``ess_bulk`` (the weights' effective sample size), ``n_proposals``, ``reason``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import xarray as xr
from scipy import stats

from .io import netcdf_attribute

METHOD = "importance sampling"
BatchFn = Callable[[np.ndarray], np.ndarray]  # theta (n, k) -> (n,)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ISSettings:
    """How many draws, from which proposal, and when the answer counts as verified."""

    seed: int
    batch: int = 1000  # draws proposed at a time (those outside the prior's support cost no simulation)
    max_draws: int = 8000  # proposals at most before the answer is declared unverified
    df: float = 5.0  # the Student-t proposal's degrees of freedom: tails heavier than the Laplace approximation's
    pareto_k_max: float = 0.7  # PSIS's bound on k̂ for a reliable estimate
    ess_min: float = 400.0  # effective sample size of the smoothed weights to reach

    def __post_init__(self):
        if self.batch < 1 or self.max_draws < self.batch:
            raise ValueError(f"need 1 <= batch <= max_draws, got batch {self.batch}, max_draws {self.max_draws}")
        if not self.df > 0:
            raise ValueError(f"df must be > 0, got {self.df}")


def sample(
    log_likelihood_batch: BatchFn,
    log_prior_batch: BatchFn,
    names: Sequence[str],
    mean: np.ndarray,
    covariance: np.ndarray,
    settings: ISSettings,
    *,
    observed: Mapping[str, xr.DataArray] | None = None,
    attrs: Mapping[str, object] | None = None,
):
    """The posterior of ``names`` from Student-t draws around ``mean`` with the shape of ``covariance``.

    ``log_prior_batch`` is −inf outside the prior's support; there the likelihood is never called.  The
    likelihood must return −inf, never NaN, where a simulation fails."""
    import arviz as az

    mean = np.asarray(mean, dtype=float)
    k = len(mean)
    scale = np.sqrt(np.diag(covariance))
    # The proposal lives in the covariance's standardized coordinates, where a shape of very different
    # scales (a stiffness of 1e6 beside a ratio of 1) stays well conditioned.
    chol = np.linalg.cholesky(covariance / np.outer(scale, scale))
    proposal = stats.multivariate_t(loc=np.zeros(k), shape=np.eye(k), df=settings.df)
    rng = np.random.default_rng(settings.seed)
    theta, log_q, log_p, log_like = (np.empty((0, k)), np.empty(0), np.empty(0), np.empty(0))
    n_proposals = 0
    while True:
        t = np.atleast_2d(proposal.rvs(settings.batch, random_state=rng)).reshape(settings.batch, k)
        x = mean + (t @ chol.T) * scale
        n_proposals += settings.batch
        lp = np.asarray(log_prior_batch(x), dtype=float)
        inside = np.isfinite(lp)
        ll = np.asarray(log_likelihood_batch(x[inside]), dtype=float) if inside.any() else np.empty(0)
        theta = np.vstack([theta, x[inside]])
        log_q = np.concatenate([log_q, proposal.logpdf(t[inside]).reshape(-1)])
        log_p = np.concatenate([log_p, lp[inside]])
        log_like = np.concatenate([log_like, ll])
        raw = np.where(np.isfinite(log_like), log_like + log_p - log_q, -np.inf)
        verdict = _verify(raw, settings)
        if verdict["converged"] or n_proposals + settings.batch > settings.max_draws:
            break
        if verdict["pareto_k"] > settings.pareto_k_max:
            break  # more draws of a proposal that misses the posterior would not mend it
    log_weight, weights = verdict.pop("log_weight"), verdict.pop("weights")
    picked = _systematic(weights, settings.batch, rng)

    def chain(values):  # (draw,) -> (chain, draw)
        return np.asarray(values)[None]

    posterior = az.dict_to_dataset({name: chain(theta[picked, i]) for i, name in enumerate(names)})
    sample_stats = az.dict_to_dataset({"lp": chain(log_like[picked] + log_p[picked]), "log_likelihood": chain(log_like[picked])})
    proposals = xr.Dataset(
        {**{name: ("proposal", theta[:, i]) for i, name in enumerate(names)},
         "log_weight": ("proposal", log_weight), "log_likelihood": ("proposal", log_like)},
        attrs={"long_name": "every proposed draw inside the prior's support, with its Pareto-smoothed log weight"},
    )
    groups = {"posterior": posterior, "sample_stats": sample_stats, "importance": proposals}
    if observed is not None:
        groups["observed_data"] = xr.Dataset(dict(observed))
    idata = az.InferenceData(**groups)
    idata.attrs = {
        **{key: netcdf_attribute(value) for key, value in (attrs or {}).items()},
        "method": METHOD,
        "proposal": f"multivariate Student-t (df {settings.df:g}) with the Laplace approximation's mean and covariance",
        "importance_settings": json.dumps(dataclasses.asdict(settings)),
        "arviz_version": az.__version__,
        "n_proposals": n_proposals,
        "n_draws": len(picked),
        **{key: netcdf_attribute(value) for key, value in verdict.items()},
    }
    return idata


def _verify(raw_log_weights: np.ndarray, settings: ISSettings) -> dict:
    """PSIS of the raw log weights: the smoothed normalized weights, k̂, their effective sample size and whether
    both meet the settings (``reason`` names what failed)."""
    import arviz as az

    finite = np.isfinite(raw_log_weights)
    log_weight = np.full(raw_log_weights.shape, -np.inf)
    if finite.sum() < 2:
        return {"log_weight": log_weight, "weights": np.zeros(raw_log_weights.shape), "pareto_k": math.inf, "ess_bulk": 0.0,
                "converged": False, "reason": "no draw of the proposal has a finite posterior density"}
    smoothed, pareto_k = az.psislw(raw_log_weights[finite])
    log_weight[finite] = smoothed
    weights = np.exp(log_weight)
    ess = float(1.0 / np.sum(weights**2))
    failed = []
    if not pareto_k <= settings.pareto_k_max:
        failed.append(f"pareto_k {pareto_k:.2f} > {settings.pareto_k_max:g}: the Laplace approximation misses the posterior")
    if not ess >= settings.ess_min:
        failed.append(f"ess {ess:.0f} < {settings.ess_min:g}")
    return {"log_weight": log_weight, "weights": weights, "pareto_k": float(pareto_k), "ess_bulk": ess,
            "converged": not failed, "reason": "; ".join(failed)}


def _systematic(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` equally weighted draws resampled from ``weights`` (normalized), systematically: each
    draw is picked within one of its expected count."""
    edges = np.cumsum(weights)
    edges[-1] = 1.0
    return np.searchsorted(edges, (rng.uniform() + np.arange(n)) / n)
