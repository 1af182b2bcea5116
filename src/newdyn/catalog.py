"""Which measurement files a diagnosis can use, remembered by each file's size and time stamp.

The Snakefile asks this while it builds the job graph, and on a cluster every job builds it again: reading
every file each time would make parsing grow with the data.  A file is read and checked (:func:`newdyn.io.
read_measurement`, :func:`newdyn.diagnosis.check_measurement`) only when the index has not seen it at its
size and time stamp under the same settings; the numerical stack is imported only then.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from . import cache

SUFFIXES = (".nc", ".csv")
NAME = re.compile(r"[A-Za-z0-9_.-]+")
CHECKS = ("io.py", "diagnosis.py")  # the modules whose code decides whether a file is good


def good_measurements(folder: str | os.PathLike, operating: Mapping[str, float], channels: Sequence[str], band_hz: float,
                      index: str | os.PathLike) -> tuple[dict[str, str], list[str]]:
    """(name → path of every good measurement in ``folder``, one line per bad file naming it and its problem).
    ``index`` is the JSON file that remembers the checks; it is rewritten only when a check was made."""
    settings = json.dumps({"operating": dict(operating), "channels": list(channels), "band_hz": band_hz, "checks": _checks_version()},
                          sort_keys=True)
    document = cache.read_json(index)
    known = document.get("files", {}) if document.get("settings") == settings else {}
    by_name: dict[str, list[Path]] = {}
    for path in sorted(Path(folder).glob("*")):
        if path.suffix.lower() in SUFFIXES:
            by_name.setdefault(path.stem, []).append(path)
    good, problems, checked, changed = {}, [], {}, False
    for name, paths in by_name.items():
        if len(paths) > 1:
            problems.append(f"{paths[0]}: {' and '.join(map(str, paths))} share the name '{name}'")
            continue
        path = paths[0]
        stat = path.stat()
        stamp = [stat.st_size, stat.st_mtime_ns]
        entry = known.get(str(path))
        if entry is None or entry["stamp"] != stamp:
            entry, changed = {"stamp": stamp, "problem": _problem(path, operating, channels, band_hz)}, True
        checked[str(path)] = entry
        problem = entry["problem"] or (None if NAME.fullmatch(name) else f"{path}: name may hold letters, digits, '_', '-' and '.' only")
        if problem:
            problems.append(problem)
        else:
            good[name] = str(path)
    if changed or set(checked) != set(known):
        cache.write_json(index, {"settings": settings, "files": checked})
    return good, problems


def _checks_version() -> str:
    """A hash of the code that reads and checks a file, so that a file refused by older checks is looked at again."""
    here = Path(__file__).parent
    return hashlib.sha256(b"".join((here / name).read_bytes() for name in CHECKS)).hexdigest()[:16]


def _problem(path: Path, operating, channels, band_hz) -> str | None:
    from . import diagnosis, io

    try:
        diagnosis.check_measurement(io.read_measurement(path, operating), channels, band_hz, path)
    except io.MeasurementError as error:
        return str(error)
    return None
