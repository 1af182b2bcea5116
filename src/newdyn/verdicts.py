"""The verdicts a diagnosis gives, as ``verdict.json`` names them, and how a reader meets them (a run's closing lines,
the report's page): shared by the diagnosis and the blind test's scoring, which must not import the diagnosis."""

import html
import json
from collections.abc import Iterable, Mapping
from pathlib import Path

from .faults import HEALTHY, PARAMETER_CHANGE

NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM = "new_dynamics", "unexplained", "sensor_problem"
VERDICTS = (HEALTHY, PARAMETER_CHANGE, NEW_DYNAMICS, UNEXPLAINED, SENSOR_PROBLEM)


def statements(paths: Iterable[str]) -> list[str]:
    """``<verdict.json>: <its statement>`` for each of ``paths`` that exists (what a run prints at its end)."""
    return [f"{path}: {json.loads(Path(path).read_text())['statement']}" for path in paths if Path(path).is_file()]


def page(verdict: Mapping, provenance: Mapping[str, str]) -> str:
    """A verdict (a file's or a machine's) as a short HTML page for the report: its statement first, then the class,
    the effect, its look-alikes and the fitted values with their 94 % HDIs; ``provenance`` in the page's metadata."""
    name = verdict.get("measurement") or verdict.get("machine")
    rows = [("verdict", verdict["verdict"]), ("effect", verdict.get("effect") or "none"),
            ("explain it as well", ", ".join(e for e in verdict.get("equivalent") or [] if e != verdict.get("effect")) or "none")]
    rows += [(parameter, f"{p['mean']:.4g} (94 % HDI {p['hdi_low']:.4g} to {p['hdi_high']:.4g})")
             for parameter, p in (verdict.get("parameters") or {}).items()]
    table = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
    meta = "".join(f'<meta name="{html.escape(k)}" content="{html.escape(str(v))}">' for k, v in provenance.items())
    return (f"<!doctype html><html><head><meta charset=\"utf-8\">{meta}<title>{html.escape(name)}</title></head><body>"
            f"<h2>{html.escape(name)}</h2><p>{html.escape(verdict['statement'])}</p><table>{table}</table></body></html>\n")
