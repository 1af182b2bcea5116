"""The verdicts a diagnosis gives, as ``verdict.json`` names them: shared by the diagnosis and the blind test's
scoring, which must not import the diagnosis to read them."""

import json
from collections.abc import Iterable
from pathlib import Path

from .faults import PARAMETER_CHANGE

HEALTHY, NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM = "healthy", "new_dynamics", "unexplained", "sensor_problem"
VERDICTS = (HEALTHY, PARAMETER_CHANGE, NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM)


def statements(paths: Iterable[str]) -> list[str]:
    """``<verdict.json>: <its statement>`` for each of ``paths`` that exists (what a run prints at its end)."""
    return [f"{path}: {json.loads(Path(path).read_text())['statement']}" for path in paths if Path(path).is_file()]
