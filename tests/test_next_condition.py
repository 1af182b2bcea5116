"""Which condition to record next: the advice against the rig's physics and the expected log Bayes factor's closed form."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from newdyn import hypotheses, model, next_condition
from newdyn.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
CONFIG = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
SETTINGS = Settings.from_config(CONFIG)
HYPOTHESES = {h.name: h for h in SETTINGS.hypotheses()}
SAMPLING = model.Sampling(fs=5000.0, t_first=0.5, n_samples=1000)  # 0.2 s: more than two load cycles
PART_LOAD = {k: model.DEFAULTS[k] for k in model.OPERATING_PARAMETERS} | {"T0": 1100.0}
# The healthy rig's joint torque (between J2a and J2b) peaks at this multiple of T0 over a load cycle, measured on the
# default rig (src/newdyn/effects/library/stick_slip.py): the joint slips once T0 passes T_max over it.
PEAK_OVER_T0 = 1.307


def fitted(name, **values):
    hypothesis = HYPOTHESES[name]
    values = {p: values.get(p, SETTINGS.rig.get(p, model.DEFAULTS.get(p))) for p in hypothesis.parameters}
    return hypotheses.JointFit(hypothesis, values, (), 0.0, (), 0.0, 0)


def advise(top, rival, snr_db=40.0, ranges=None):
    return next_condition.rank(top, [rival], PART_LOAD, ranges or SETTINGS.operating_range, SETTINGS.rig, SAMPLING,
                               SETTINGS.channels, snr_db, SETTINGS.max_step, SETTINGS.evidence_margin,
                               np.random.default_rng(0))


@pytest.mark.parametrize("t_max", [1700.0, 1854.95])
def test_a_stick_slip_is_told_from_healthy_from_the_load_at_which_its_joint_starts_to_slip(t_max):
    advice = advise(fitted("healthy"), fitted("stick_slip", T_max=t_max, r_k=1.0, J2a_share=1 / 3))
    row = advice["rivals"][0]
    assert row["advice"]["parameter"] == "T0" and row["advice"]["high"] is None  # the whole range above it
    assert row["advice"]["low"] == pytest.approx(t_max / PEAK_OVER_T0, rel=0.03)
    below = [c for c in row["candidates"] if c["parameter"] == "T0" and c["value"] < 0.97 * t_max / PEAK_OVER_T0]
    assert below and all(c["expected_log_bayes_factor"] == 0.0 for c in below)  # stuck: the same rig as healthy
    assert next_condition.sentence(advice).startswith(f"record at T0 >= {row['advice']['low']:.4g} N·m to tell healthy "
                                                      "from stick_slip")


def test_a_drift_of_nothing_is_told_from_healthy_nowhere():
    advice = advise(fitted("healthy"), fitted("parameter_change:kT1"))
    assert not advice["rivals"][0]["advice"]["separates"]
    assert max(c["expected_log_bayes_factor"] for c in advice["rivals"][0]["candidates"]) < 1e-12
    assert next_condition.sentence(advice) == ("no condition in the operating range would tell healthy from "
                                               "parameter_change:kT1 at this noise level")


def test_the_expected_log_bayes_factor_grows_as_the_noise_power_falls():
    """½ Σ ((m_a − m_b)/σ)² with σ at the SNR: 10 dB more is ten times the factor at every condition."""
    top, rival, ranges = fitted("healthy"), fitted("parameter_change:kT1", kT1=3.15e6), {"speed_rpm": (1000.0, 1500.0)}
    at_40, at_50 = (np.array([c["expected_log_bayes_factor"] for c in advise(top, rival, snr, ranges)["rivals"][0]["candidates"]])
                    for snr in (40.0, 50.0))
    assert np.all(at_40 > 0) and at_50 == pytest.approx(10 * at_40, rel=1e-9)
