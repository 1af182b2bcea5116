"""What a diagnosis needs from a study's config: the rig, the channels compared, the calibration's grids and priors,
the effects' ranges, the evidence and noise settings, the instruments and the operating range
(:meth:`Settings.from_config`; every key in config/README.md)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from . import calibration, hypotheses, noise, study
from . import posterior as posterior_module
from . import sensors as sensors_module


@dataclass(frozen=True)
class Settings:
    """What a diagnosis needs from config (see ``Settings.from_config`` and config/README.md)."""

    rig: Mapping[str, float]
    channels: tuple[str, ...]
    grids: Mapping[str, calibration.GridSpec]
    priors: Mapping[str, calibration.NormalPrior]
    fault_ranges: Mapping[str, Mapping[str, tuple[float, float]]]
    drift: tuple[str, ...]
    severities: int
    drift_sizes: tuple[float, ...]
    noise_band_hz: float
    evidence_margin: float
    chi2_max: float
    refine_points: int
    max_step: float
    posterior: posterior_module.PosteriorSettings
    mcmc: Mapping[str, float | int | str] = field(default_factory=dict)
    discovery: str = "unexplained"  # or "always", "never"
    sensors: Mapping[str, sensors_module.Sensor] = field(default_factory=dict)  # instrument errors per channel
    noise_colour_order: int = 0  # highest AR order of the noise's colour; 0: white
    operating_range: Mapping[str, tuple[float, float]] = field(default_factory=dict)  # where a next recording may be made

    @classmethod
    def from_config(cls, config: Mapping) -> Settings:
        """From a study config (or a diagnosis spec holding its rig, diagnosis, calibration and
        simulation sections); the effects' ranges by :func:`newdyn.study.diagnosis_ranges`."""
        d, c = config["diagnosis"], config["calibration"]
        return cls(
            rig=dict(config["rig"]),
            channels=tuple(d["channels"]),
            grids={p: calibration.GridSpec.from_config(p, s["grid"]) for p, s in c["parameters"].items()},
            priors={p: calibration.NormalPrior(**s["prior"]) for p, s in c["parameters"].items()},
            fault_ranges={kind: {n: (float(low), float(high)) for n, (low, high) in ranges.items()}
                          for kind, ranges in study.diagnosis_ranges(config).items()},
            drift=tuple(d["drift"]),
            severities=int(d["severities"]),
            drift_sizes=tuple(float(x) for x in d["drift_sizes"]),
            noise_band_hz=float(d["noise_band_hz"]),
            evidence_margin=float(d["evidence_margin"]),
            chi2_max=float(c["chi2_max"]),
            refine_points=int(c["refine_points"]),
            max_step=float(config["simulation"]["max_step"]),
            mcmc={**{k: c["mcmc"][k] for k in ("rhat_max", "ess_min", "move", "max_rounds")}, **d["mcmc"]},
            posterior=posterior_module.PosteriorSettings.from_config(d["mcmc"]["seed"], c["mcmc"]["ess_min"],
                                                                     d.get("posterior", {})),
            discovery=d.get("discovery", "unexplained"),
            sensors={c: sensors_module.Sensor(**spec) for c, spec in d.get("sensors", {}).items()},
            noise_colour_order=int(d.get("noise_colour_order", 0)),
            operating_range={p: (float(low), float(high)) for p, (low, high) in config.get("operating_range", {}).items()},
        )

    def searches(self, explained: bool) -> bool:
        """Whether to look for a missing term outside the library, given whether something of it ``explained`` the data."""
        return self.discovery == "always" or (self.discovery == "unexplained" and not explained)

    def instruments(self, fs: float, colour: noise.Colour | None = None) -> sensors_module.Instruments | None:
        """The diagnosis channels' instrument errors at sampling rate ``fs`` and their noise's ``colour``; None
        when all are exact and the noise white."""
        return sensors_module.Instruments.of(self.sensors, self.channels, fs, colour)

    def calibration_priors(self) -> dict[str, hypotheses.Prior]:
        return {
            p: hypotheses.Prior(p, self.grids[p].low, self.grids[p].high, self.priors[p].mean, self.priors[p].sd)
            for p in self.grids
        }

    def hypotheses(self) -> list[hypotheses.Hypothesis]:
        return hypotheses.library(self.calibration_priors(), self.fault_ranges, self.drift)
