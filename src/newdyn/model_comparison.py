"""Model versions compared the ArviZ way: pointwise log-likelihoods in blocks, PSIS-LOO, ``az.compare``.

A diagnosis's model versions (nominal, calibrated, + library effect, + discovered term) are each a fit
with a posterior of its parameters.  The Gaussian log-likelihood of the data, summed within blocks of
one channel over one load cycle, is evaluated at draws of that posterior: blocks small enough to keep
and many enough for leave-one-out, a block being what a new load cycle of one sensor would bring.
``az.loo`` per version and ``az.compare`` across them then rank the versions by expected log predictive
density, leaving one load cycle of one channel out.  With instrument errors (:mod:`newdyn.sensors`) each draw's
outputs are read through the instruments' offsets and gains at their posterior means given that draw.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np

from . import likelihood, sensors

DRAWS = 128  # posterior draws per model version


def cycles(times: np.ndarray, load_freq: float) -> np.ndarray:
    """Each sample's load cycle, counted from the record's first sample."""
    return np.floor((times - times[0]) * load_freq + 1e-9).astype(int)


def pointwise(data: np.ndarray, sigma: np.ndarray, outputs: np.ndarray, cycle: np.ndarray, instruments: sensors.Instruments | None = None) -> np.ndarray:
    """Log-likelihood (draw, channel, cycle) of ``data`` (channel, time) under model ``outputs`` (draw,
    channel, time), summed over the samples of each channel within each load cycle (whitened ones, when the
    instruments' noise is coloured)."""
    outputs = sensors.reading(data, outputs, sigma, instruments)
    colour = instruments.colour if instruments is not None else None
    if colour is not None:
        (data, sigma, cycle), outputs = colour.seen(data, sigma, cycle), colour.whiten(outputs)
    return np.stack([likelihood.log_likelihood(data[:, cycle == c], outputs[..., cycle == c], sigma, per_channel=True)
                     for c in range(int(cycle.max()) + 1)], axis=-1)


def draws(mean: np.ndarray, covariance: np.ndarray | None, low: np.ndarray, high: np.ndarray, rng: np.random.Generator,
          n: int = DRAWS) -> np.ndarray:
    """(n, k) draws of a Normal (Laplace) posterior truncated to the prior box; the mean alone without a covariance."""
    if covariance is None or len(mean) == 0:
        return np.repeat(np.atleast_2d(mean), n, axis=0)
    kept = np.empty((0, len(mean)))
    while len(kept) < n:
        proposed = rng.multivariate_normal(mean, covariance, 4 * n)
        kept = np.vstack([kept, proposed[np.all((proposed >= low) & (proposed <= high), axis=1)]])
    return kept[:n]


def inference_data(log_likelihood: np.ndarray, parameters: Mapping[str, np.ndarray], channels: Sequence[str]):
    """InferenceData of one version: its draws (one chain) and the pointwise log-likelihood (channel, cycle)."""
    import arviz as az

    # A version without parameters (the nominal model) gets its one constant, so that loo has a posterior.
    posterior = {name: values[None] for name, values in parameters.items()} or {"no_parameters": np.zeros((1, len(log_likelihood)))}
    return az.from_dict(posterior=posterior, log_likelihood={"y": log_likelihood[None]},
                        coords={"channel": list(channels), "cycle": np.arange(log_likelihood.shape[-1])},
                        dims={"y": ["channel", "cycle"]})


PARETO_K_MAX = 0.7  # above it, a block's PSIS-LOO estimate is unreliable (ArviZ's threshold for its warning)


def compare(versions: Mapping[str, object]) -> list[dict]:
    """``az.compare`` of the versions' InferenceData by PSIS-LOO: one row per version, best first, with ``warning``
    true only where some block's Pareto k̂ exceeds :data:`PARETO_K_MAX`, and ``warning_reason`` saying how many.  A
    version without parameters has one model for every draw: leaving a block out changes nothing, its elpd_loo is its
    log-likelihood exactly, and ArviZ's flag for its undefined k̂ is no warning."""
    import warnings

    import arviz as az

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a constant version's Pareto k is undefined: handled below
        table = az.compare(dict(versions), ic="loo", method="pseudo-BMA")
        pareto_k = {name: np.asarray(az.loo(idata, pointwise=True).pareto_k).ravel() for name, idata in versions.items()}
    rows = []
    for name, row in table.iterrows():
        exact = "no_parameters" in versions[name].posterior
        flagged = 0 if exact else int(np.sum(pareto_k[name] > PARETO_K_MAX))
        rows.append({
            "version": str(name), "rank": int(row["rank"]),
            **{key: float(row[key]) for key in ("elpd_loo", "p_loo", "elpd_diff", "weight", "se", "dse")},
            "pareto_k_max": None if exact else float(np.max(pareto_k[name])),
            "warning": flagged > 0,
            "warning_reason": "" if not flagged else (
                f"Pareto k above {PARETO_K_MAX:g} at {flagged} of {pareto_k[name].size} blocks: leaving those out moves "
                "this version's posterior more than importance sampling can follow, so its elpd_loo is approximate "
                "there (a version that misfits some load cycles does this)"),
        })
    return rows


class Version(NamedTuple):
    """A model version to compare: its outputs for a batch of draws, the draws, and what it is seen through."""

    simulate: Callable[[np.ndarray], np.ndarray]  # draws (n, k) -> outputs (n, channel, time)
    draws: np.ndarray
    names: Sequence[str]  # the draws' parameters
    instruments: sensors.Instruments | None = None


def evaluate_versions(versions: Mapping[str, Version], data: np.ndarray, sigma: np.ndarray, cycle: np.ndarray,
                      channels: Sequence[str]) -> dict:
    """InferenceData per version."""
    return {name: inference_data(pointwise(data, sigma, v.simulate(v.draws), cycle, v.instruments), dict(zip(v.names, v.draws.T)), channels)
            for name, v in versions.items()}
