"""The verdicts a diagnosis gives, as ``verdict.json`` names them: shared by the diagnosis and the blind test's
scoring, which must not import the diagnosis to read them."""

from .faults import PARAMETER_CHANGE

HEALTHY, NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM = "healthy", "new_dynamics", "unexplained", "sensor_problem"
VERDICTS = (HEALTHY, PARAMETER_CHANGE, NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM)
