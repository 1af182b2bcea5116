"""The names in a hidden set, from its config alone: the workflow reads them while it parses, so this imports no
simulator."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def case_names(set_name: str, cases: int) -> list[str]:
    """The names of a set's cases: ``<set>_01`` …"""
    width = max(2, len(str(cases)))
    return [f"{set_name}_{i + 1:0{width}d}" for i in range(cases)]


def recording_names(set_name: str, spec: Mapping) -> dict[str, list[str]]:
    """A machine set's machines and their recordings' names (``<machine>/r<k>``), their number drawn in the set's
    ``recordings`` range from its seed alone."""
    rng = np.random.default_rng(np.random.SeedSequence([int(spec["seed"]), 2]))
    low, high = spec["recordings"]
    return {name: [f"{name}/r{k + 1}" for k in range(int(rng.integers(low, high + 1)))]
            for name in case_names(set_name, int(spec["cases"]))}
