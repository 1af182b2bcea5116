"""newdyn.residuals against closed forms and white noise: band and phase excess, the time-frequency map,
the false-alarm rate of where_it_fails, what it flags for a tone and a phase-locked burst; and the figure."""

import json

import numpy as np
import pytest
import scipy.stats

from newdyn import model, plots
from newdyn.residuals import (
    DEFAULT_BANDS,
    load_phase,
    phase_excess,
    spectral_excess,
    time_frequency_map,
    where_it_fails,
)

SAMPLING = model.Sampling()
TIMES, FS = SAMPLING.times, SAMPLING.fs
CHANNELS = ["b1_x", "w1"]
SIGMA = np.array([2e-8, 0.05])
LOAD_HZ = 12.0


def white(seed: int) -> np.ndarray:
    return SIGMA[:, None] * np.random.default_rng(seed).standard_normal((len(CHANNELS), SAMPLING.n_samples))


def band_index(low: float) -> int:
    return [band[0] for band in DEFAULT_BANDS].index(low)


def test_band_excess_of_a_pure_tone_is_its_closed_form():
    # A cos on a DFT bin puts n·A²/4 into one periodogram bin P_k: T = 2·n·A²/4 over the band's dof.
    amplitude, n = 0.5, SAMPLING.n_samples
    tone = amplitude * np.cos(2 * np.pi * 50.0 * TIMES)[None, :]
    result = spectral_excess(tone, np.array([1.0]), FS)
    k = band_index(40.0)
    assert result.dof[k] == 80  # 40 bins of 1 Hz, 2 dof each
    assert result.excess[0, k] == pytest.approx(n * amplitude**2 / 2 / 80, rel=1e-9)
    assert result.p_value[0, k] == pytest.approx(scipy.stats.chi2.sf(n * amplitude**2 / 2, 80), rel=1e-6)
    assert np.all(np.delete(result.excess[0], k) < 1e-20)
    # 0 and Nyquist bins carry one dof: 0–10 Hz has 10 bins and 19 dof, the last band up to 2500 Hz inclusive.
    assert result.dof[0] == 19 and result.dof[-1] == 2 * 1220 + 1
    assert result.bands[-1, 1] == FS / 2


def test_band_excess_of_white_noise_has_mean_one_and_uniform_p_values():
    results = [spectral_excess(white(seed), SIGMA, FS) for seed in range(200)]
    excess = np.stack([r.excess for r in results])  # (seed, channel, band)
    dof = results[0].dof
    # Each band's excess is χ²(dof)/dof: mean 1 and sd √(2/dof), here averaged over 400 records.
    se = np.sqrt(2 / dof) / np.sqrt(excess.shape[0] * excess.shape[1])
    assert np.all(np.abs(excess.mean(axis=(0, 1)) - 1) < 4 * se)
    p_values = np.concatenate([r.p_value.ravel() for r in results])
    assert scipy.stats.kstest(p_values, "uniform").pvalue > 1e-3


def test_phase_excess_of_a_constant_is_its_square_in_every_bin():
    result = phase_excess(np.full((1, SAMPLING.n_samples), 0.3), np.array([0.2]), TIMES, LOAD_HZ)
    # 5000 samples over 12 cycles of 24 bins: 208 per bin, and 4 more in bins 0 and 12, where every 625th
    # sample lies exactly on the bin's start.
    assert result.counts.sum() == SAMPLING.n_samples and set(result.counts) == {208, 212}
    np.testing.assert_allclose(result.excess, 2.25, rtol=1e-12)
    np.testing.assert_allclose(result.p_value[0], scipy.stats.chi2.sf(2.25 * result.counts, result.counts))


def test_phase_excess_of_white_noise_is_chi_square():
    p_values = np.concatenate([phase_excess(white(seed), SIGMA, TIMES, LOAD_HZ).p_value.ravel() for seed in range(100)])
    assert scipy.stats.kstest(p_values, "uniform").pvalue > 1e-3


def test_time_frequency_map_of_white_noise_is_one_everywhere():
    maps = np.stack([time_frequency_map(white(seed), SIGMA, FS, t_first=TIMES[0])[2] for seed in range(100)])
    frequency, segment_times, _ = time_frequency_map(white(0), SIGMA, FS, t_first=TIMES[0])
    assert maps.shape == (100, 2, frequency.size, segment_times.size)
    assert segment_times[0] == pytest.approx(TIMES[0] + 128 / FS)
    # Per frequency row over 100 seeds × 2 channels × 38 segments: cells are χ²₂/2 (sd 1), χ²₁ (sd √2) at 0
    # and Nyquist; half-overlapping Hann segments correlate (ρ² ≈ 0.17), so allow 5 nominal standard errors.
    cells = maps.shape[0] * maps.shape[1] * maps.shape[3]
    row_sd = np.where((frequency == 0) | (frequency == FS / 2), np.sqrt(2), 1.0)
    assert np.all(np.abs(maps.mean(axis=(0, 1, 3)) - 1) < 5 * row_sd / np.sqrt(cells))
    # One record's whole map: within 5 nominal standard errors too.
    assert np.all(np.abs(maps.mean(axis=(2, 3)) - 1) < 5 / np.sqrt(frequency.size * segment_times.size))


def test_where_it_fails_rarely_alarms_on_white_noise():
    alarms = sum(bool(where_it_fails(white(seed), SIGMA, CHANNELS, TIMES, FS, LOAD_HZ, alpha=1e-2)) for seed in range(50))
    assert alarms <= 1
    assert where_it_fails(white(0), SIGMA, CHANNELS, TIMES, FS, LOAD_HZ) == []


def test_a_small_tone_is_flagged_in_its_band_only():
    residual = white(1)
    residual[1] += 0.3 * SIGMA[1] * np.cos(2 * np.pi * 50.0 * TIMES + 1.0)
    findings = where_it_fails(residual, SIGMA, CHANNELS, TIMES, FS, LOAD_HZ)
    assert [(f["channel"], f["kind"], f["low_hz"], f["high_hz"]) for f in findings] == [("w1", "band", 40.0, 80.0)]
    # Expected excess: 1 + (n·A²/4)/40 bins = 1 + 112.5/40.
    assert findings[0]["excess"] == pytest.approx(1 + 112.5 / 40, abs=4 * np.sqrt(2 / 80))
    json.dumps(findings)


def test_a_burst_at_one_load_phase_is_flagged_there_only():
    residual = white(2)
    burst = (load_phase(TIMES, LOAD_HZ) >= 0.5) & (load_phase(TIMES, LOAD_HZ) < 0.6)
    residual[0] += burst * 2 * SIGMA[0] * np.sin(2 * np.pi * 300.0 * TIMES)
    findings = where_it_fails(residual, SIGMA, CHANNELS, TIMES, FS, LOAD_HZ)
    assert {f["channel"] for f in findings} == {"b1_x"}
    (window,) = [f for f in findings if f["kind"] == "phase"]
    # Bins of 1/24: the window covers 0.5–0.6 and at most the bin either side.
    assert 0.5 - 1 / 24 - 1e-12 <= window["phase_low"] <= 0.5 and 0.6 <= window["phase_high"] <= 0.6 + 1 / 24 + 1e-12
    assert window["excess"] > 2
    assert [f["excess"] for f in findings] == sorted((f["excess"] for f in findings), reverse=True)


def test_a_phase_window_across_the_cycle_start_is_one_window():
    residual = white(3)
    phase = load_phase(TIMES, LOAD_HZ)
    residual[1] += ((phase >= 0.95) | (phase < 0.05)) * 3 * SIGMA[1]
    (window,) = [f for f in where_it_fails(residual, SIGMA, CHANNELS, TIMES, FS, LOAD_HZ) if f["kind"] == "phase"]
    assert window["channel"] == "w1"
    assert window["phase_low"] < 0.95 and 1.05 <= window["phase_high"] < 1.1


def test_bands_without_a_frequency_bin_are_refused():
    with pytest.raises(ValueError, match="no frequency bin"):
        spectral_excess(white(0), SIGMA, FS, bands=[(10.2, 10.7)])


def test_residual_map_writes_png_and_pdf_with_two_panels_per_channel(tmp_path):
    residual = white(4)
    residual[1] += 0.3 * SIGMA[1] * np.cos(2 * np.pi * 50.0 * TIMES)
    fig = plots.residual_map(residual, SIGMA, CHANNELS, TIMES, FS, LOAD_HZ, tmp_path / "residual_map.png", "test")
    assert (tmp_path / "residual_map.png").stat().st_size > 0 and (tmp_path / "residual_map.pdf").stat().st_size > 0
    assert len(fig.axes) == 2 * len(CHANNELS) + 1  # and one shared colour bar
    # The flagged band gets a red bar on w1's map (axes row by row), none on b1_x's, which is noise only.
    def red_bars(ax):
        return [patch for patch in ax.patches if patch.get_facecolor()[:3] == (1.0, 0.0, 0.0)]

    assert len(red_bars(fig.axes[2])) == 1 and not red_bars(fig.axes[0])
