"""Which operating condition to record next, where a machine's recordings leave hypotheses equivalent.

Each candidate condition is the reference recording's condition with one operating parameter moved across the rig's
operating range (the config's ``operating_range``).  At each, the verdict's model (at its fit) is compared with each
rival that explains the recordings as well, as unmeasured channels are ranked (``diagnosis._separating_channels``): by
the expected log Bayes factor ½ Σ ((m_top − m_rival)/σ)², σ at the recordings' SNR — here averaged over draws of the
rival's posterior (its Laplace approximation, inside its prior), since what the recordings so far leave open is
exactly what they cannot pin: a stick-slip that never slipped at part load has a static limit anywhere above the
part-load torque, and how high a load reveals it depends on where.  The average is over the rival's parameters as
they stand; refitted to a new recording the rival could close part of the gap, so the figure is an upper bound, close
where the recordings pin its parameters.  A rival that is the verdict's model at every plausible value (a drift of
nothing, an effect of no size) is told apart nowhere, and said so.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from . import hypotheses, model, simulation, slots

POINTS = 9  # candidate values of each operating parameter, evenly across its range
BISECTIONS = 5  # halvings of the grid step that place where a rival starts (or stops) being told apart
DRAWS = 8  # draws of a rival's posterior the expected log Bayes factor averages over


def rank(top: hypotheses.JointFit, rivals: Sequence[hypotheses.JointFit], reference: Mapping[str, float],
         ranges: Mapping[str, Sequence[float]], rig: Mapping[str, float], sampling: model.Sampling,
         channels: Sequence[str], snr_db: float, max_step: float, margin: float, rng: np.random.Generator) -> dict:
    """Per rival of ``top``: the expected log Bayes factor between them at each candidate condition, and the advice
    read from it (the operating parameter whose move tells them apart best, and the stretch of its range that does)."""

    rows = []
    for rival in rivals:
        draws = _posterior_draws(rival, rng)

        def at(parameter, values, rival=rival, draws=draws):
            conditions = [{**reference, parameter: value} for value in values]
            return _expected_log_bayes_factors(top, rival.hypothesis, draws, conditions, rig, sampling, channels,
                                               snr_db, max_step)

        candidates = []
        for parameter, (low, high) in ranges.items():
            spec = model.PARAMETER_BY_NAME[parameter]
            values = [spec.rounded(v) for v in np.linspace(low, high, POINTS)]
            candidates += [{"parameter": parameter, "value": value, "unit": spec.unit, "expected_log_bayes_factor": factor}
                           for value, factor in zip(values, at(parameter, values))]
        rows.append({"rival": rival.hypothesis.name, "candidates": candidates, "advice": _advice(candidates, margin, at)})
    return {"model": top.hypothesis.name, "reference": dict(reference), "channels": list(channels), "snr_db": snr_db,
            "rivals": rows}


def _posterior_draws(fit: hypotheses.JointFit, rng: np.random.Generator) -> np.ndarray:
    """(DRAWS, k) draws of a fit's Laplace approximation, each parameter kept inside its prior; the fit itself where it
    has no covariance."""
    if fit.covariance is None or not fit.hypothesis.priors:
        return fit.theta[None]
    low, high = np.array([[p.low, p.high] for p in fit.hypothesis.priors]).T
    return np.clip(rng.multivariate_normal(fit.theta, fit.covariance, DRAWS), low, high)


def _expected_log_bayes_factors(top: hypotheses.JointFit, rival: hypotheses.Hypothesis, draws: np.ndarray,
                                conditions: Sequence[Mapping[str, float]], rig: Mapping[str, float],
                                sampling: model.Sampling, channels: Sequence[str], snr_db: float,
                                max_step: float) -> list[float]:
    """Per condition, ½ Σ ((m_top − m_rival)/σ)² averaged over the rival's ``draws``; all runs in one batch each."""
    bases = [slots.complete({**rig, **c}) for c in conditions]
    expected = simulation.simulate_batch(
        np.concatenate([top.hypothesis.parameter_rows(top.theta[None], base) for base in bases]), sampling, channels, max_step)
    rivals = simulation.simulate_batch(
        np.concatenate([rival.parameter_rows(draws, base) for base in bases]), sampling, channels, max_step
    ).reshape(len(bases), len(draws), len(channels), -1)
    noise_sd = np.std(expected, axis=-1) * 10 ** (-snr_db / 20)
    return [float(np.mean(0.5 * np.sum(((rivals[k] - expected[k]) / noise_sd[k][:, None]) ** 2, axis=(1, 2))))
            for k in range(len(bases))]


def _advice(candidates: Sequence[Mapping], margin: float, at: Callable[[str, list[float]], list[float]]) -> dict:
    """The operating parameter whose move tells the pair apart best, and the stretch of its range around that best
    value where the expected log Bayes factor passes ``margin``, its ends placed by bisection between the grid's
    values."""
    best = max(candidates, key=lambda c: c["expected_log_bayes_factor"])
    parameter, separates = best["parameter"], best["expected_log_bayes_factor"] > margin
    advice = {"parameter": parameter, "unit": best["unit"], "value": best["value"],
              "expected_log_bayes_factor": best["expected_log_bayes_factor"], "separates": separates}
    if not separates:
        return advice
    own = [c for c in candidates if c["parameter"] == parameter]
    first = last = own.index(best)
    while first > 0 and own[first - 1]["expected_log_bayes_factor"] > margin:
        first -= 1
    while last < len(own) - 1 and own[last + 1]["expected_log_bayes_factor"] > margin:
        last += 1
    spec = model.PARAMETER_BY_NAME[parameter]

    def edge(outside, inside):
        for _ in range(BISECTIONS):
            middle = spec.rounded((outside + inside) / 2)
            if middle in (outside, inside):
                break
            outside, inside = (outside, middle) if at(parameter, [middle])[0] > margin else (middle, inside)
        return inside

    advice["low"] = edge(own[first - 1]["value"], own[first]["value"]) if first > 0 else None
    advice["high"] = edge(own[last + 1]["value"], own[last]["value"]) if last < len(own) - 1 else None
    return advice


def sentence(record_next: Mapping) -> str:
    """The advice plainly: "record at T0 >= 1420 N·m to tell healthy from stick_slip (...)", and the rivals no
    condition in the range tells from the verdict's model."""
    top = record_next["model"]
    parts, nowhere = [], []
    for row in record_next["rivals"]:
        a = row["advice"]
        p, unit = a["parameter"], a["unit"]
        if not a["separates"]:
            nowhere.append(row["rival"])
            continue
        if a["low"] is None and a["high"] is None:
            where = f"any {p} in the range"
        elif a["high"] is None:
            where = f"{p} >= {a['low']:.4g} {unit}"
        elif a["low"] is None:
            where = f"{p} <= {a['high']:.4g} {unit}"
        else:
            where = f"{p} between {a['low']:.4g} and {a['high']:.4g} {unit}"
        parts.append(f"record at {where} to tell {top} from {row['rival']} (expected log Bayes factor "
                     f"{a['expected_log_bayes_factor']:.3g} at {p} {a['value']:.4g} {unit})")
    if nowhere:
        parts.append(f"no condition in the operating range would tell {top} from {', '.join(nowhere)} at this noise level")
    return "; ".join(parts)
