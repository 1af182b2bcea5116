"""A diagnosis's verdict in words: the one sentence that opens ``verdict.json`` (what explains the data, with which
values, how far the error fell, or where the best model still fails; the instruments; the channels it lacked)."""

from __future__ import annotations

from collections.abc import Mapping

from .discovery import verify
from .verdicts import SENSOR_PROBLEM


def statement(verdict: Mapping, chi2_max: float) -> str:
    """The verdict in one plain sentence: what explains the data, with which values, and how far the
    error fell; or, when nothing does, where the best model's residual remains above the noise; then, with a
    sensor model, the instruments out of their spec and how much of the misfit the instruments took."""
    return _with_instruments(verdict, chi2_max) + "".join(_missing_sentence(row) for row in verdict.get("missing_channels", []))


def _missing_sentence(row: Mapping) -> str:
    pair, factor = " and ".join(row["between"]), f"expected log Bayes factor {row['expected_log_bayes_factor']:.3g} at this SNR"
    if not row["equivalent"]:
        return (f"; the recording lacks {row['channel']}, not needed for this verdict (it would add an {factor} between "
                f"{row['between'][0]} and its closest rival {row['between'][1]})")
    if row["separates"]:
        return f"; the recording lacks {row['channel']}, which would tell {pair} apart ({factor})"
    return f"; the recording lacks {row['channel']}, which would not tell {pair} apart either ({factor})"


def _with_instruments(verdict: Mapping, chi2_max: float) -> str:
    """:func:`statement` without the missing channels."""
    if "instruments_took" not in verdict:
        return _model_sentence(verdict, chi2_max)
    problems = "; ".join(p["statement"] for p in verdict["sensor_problems"])
    if verdict["verdict"] == SENSOR_PROBLEM:
        sentence = (f"sensor problem: {problems}, outside the datasheet's spread; seen through that, the nominal model "
                    f"explains the data (reduced chi2 {verdict['chi2_before']:.3g} <= {chi2_max:g})")
    else:
        sentence = _model_sentence(verdict, chi2_max) + (f"; out of spec: {problems}" if problems else "")
    for alternative in verdict.get("sensor_alternatives", []):
        sentence += (f"; {alternative['hypothesis']} explains the data as well through an instrument out of its spec ("
                     + "; ".join(p["statement"] for p in alternative["sensor_problems"])
                     + "): only the prior odds against a bad instrument chose, a check of that sensor would tell")
    took = verdict["instruments_took"]
    exact, through = f"{took['chi2_exact']:.3g}", f"{took['chi2']:.3g}"
    if exact == through:  # the instruments took nothing worth a word
        return sentence
    return sentence + (f"; the instruments' offsets, gains and delays took the final model's reduced chi2 from "
                       f"{exact} (exact instruments) to {through}")


def _model_sentence(verdict: Mapping, chi2_max: float) -> str:
    """What the final model says: :func:`statement` without the instruments."""
    before, after = verdict["chi2_before"], verdict["chi2_after"]
    fitted = ", ".join(f"{name} = {p['mean']:.4g} (94 % HDI {p['hdi_low']:.4g} to {p['hdi_high']:.4g})"
                       for name, p in verdict["parameters"].items())
    kind, effect = verdict["verdict"], verdict["effect"]
    if kind == "healthy":
        return f"healthy: the nominal model explains the data (reduced chi2 {before:.3g} <= {chi2_max:g})"
    if kind == "parameter_change":
        others = [e for e in verdict["equivalent"] if e != effect]
        return (f"parameter change: {fitted} brings reduced chi2 from {before:.3g} to {after:.3g}"
                + (f"; a drift of {' or '.join(others)} explains the data equally well (see identifiability)" if others else ""))
    if kind == "new_dynamics":
        return (f"new dynamics: {effect} added to the model, with {fitted}, brings reduced chi2 from {before:.3g} to {after:.3g}"
                + (_unreliable(verdict["effect_fit"]) if verdict.get("converged") is False else ""))
    where = "; ".join(_finding(f) for f in verdict["remaining"][:3]) or "no single band or load phase"
    return (f"unexplained: no hypothesis of the library brings reduced chi2 to {chi2_max:g} or below; the closest, "
            f"{verdict['models']['after']}, leaves {after:.3g}, above the noise in {where}"
            + (f"; {verify.in_words(verdict['discovery'], before)}" if verdict.get("discovery", {}).get("candidates") else ""))


def _unreliable(effect_fit: Mapping) -> str:
    """What an unconverged posterior's intervals are worth, in words."""
    method = "MCMC" if effect_fit["method"] == "mcmc" else effect_fit["method"]
    return f"; these intervals are not reliable: the {method} did not converge ({effect_fit.get('reason') or 'its diagnostics failed'})"


def _finding(finding: Mapping) -> str:
    """A finding of :func:`residuals.where_it_fails` in words."""
    if finding["kind"] == "band":
        return f"{finding['channel']} {finding['low_hz']:g}-{finding['high_hz']:g} Hz (x{finding['excess']:.3g} the noise power)"
    return (f"{finding['channel']} at load-cycle phase {finding['phase_low']:.3g}-{finding['phase_high']:.3g} "
            f"(x{finding['excess']:.3g} the noise power)")
