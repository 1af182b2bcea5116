"""Which measurement files a diagnosis can use, remembered by each file's size and time stamp.

The Snakefile asks this while it builds the job graph, and on a cluster every job builds it again: reading
every file each time would make parsing grow with the data.  A file is read and checked (:func:`newdyn.io.
read_measurement`, :func:`newdyn.measurement_checks.check_measurement`) only when the index has not seen it at its
size and time stamp under the same settings; the numerical stack is imported only then.  A folder of recordings
in the measurements folder is a machine: its files are named `<machine>/<recording>`.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from . import cache
from .measurement_files import CONDITIONS, NAME, SUFFIXES

CHECKS = ("io.py", "running_speed.py", "measurement_checks.py")  # the modules whose code decides whether a file is good
# The folders of a machine's own results (results/diagnosis/<machine>/), beside each of its recordings' results there:
# no recording may take their names.
MACHINE_FOLDERS = ("discovery", "figures")


def good_measurements(folder: str | os.PathLike, operating: Mapping[str, float], channels: Sequence[str], band_hz: float,
                      index: str | os.PathLike | None, rig: Mapping[str, float] | None = None) -> tuple[dict[str, str], list[str]]:
    """(name → path of every good measurement in ``folder``, one line per bad file naming it and its problem).
    ``index`` is the JSON file that remembers the checks; it is rewritten only when a check was made.  Without one,
    every file is checked and nothing is remembered.  With the ``rig``, each channel's level is checked too."""
    settings = json.dumps({"operating": dict(operating), "channels": list(channels), "band_hz": band_hz, "checks": _checks_version(),
                           "rig": dict(rig or {})}, sort_keys=True)
    document = cache.read_json(index) if index is not None else {}
    known = document.get("files", {}) if document.get("settings") == settings else {}
    by_name: dict[str, list[Path]] = {}
    for path in sorted([*Path(folder).glob("*"), *Path(folder).glob("*/*")]):  # a machine's recordings: <machine>/<recording>
        if path.suffix.lower() in SUFFIXES and path.name != CONDITIONS and path.is_file():
            by_name.setdefault(path.relative_to(folder).with_suffix("").as_posix(), []).append(path)
    machines = {name.split("/")[0] for name in by_name if "/" in name}
    good, problems, checked, changed = {}, [], {}, False
    for name, paths in by_name.items():
        if len(paths) > 1:
            problems.append(f"{paths[0]}: {' and '.join(map(str, paths))} share the name '{name}'")
            continue
        if name in machines:
            problems.append(f"{paths[0]}: shares its name with the machine folder {Path(folder) / name}; rename one of them")
            continue
        path = paths[0]
        stamp = [[stat.st_size, stat.st_mtime_ns] for stat in (p.stat() for p in (path, path.parent / CONDITIONS) if p.is_file())]
        entry = known.get(str(path))
        if entry is None or entry["stamp"] != stamp:
            entry, changed = {"stamp": stamp, "problem": _problem(path, operating, channels, band_hz, rig)}, True
        checked[str(path)] = entry
        problem = entry["problem"] or name_problem(path, name)
        if problem:
            problems.append(problem)
        else:
            good[name] = str(path)
    if index is not None and (changed or set(checked) != set(known)):
        cache.write_json(index, {"settings": settings, "files": checked})
    return good, problems


def _checks_version() -> str:
    """A hash of the code that reads and checks a file, so that a file refused by older checks is looked at again."""
    here = Path(__file__).parent
    return hashlib.sha256(b"".join((here / name).read_bytes() for name in CHECKS)).hexdigest()[:16]


def checked_measurement(path: str | os.PathLike, operating: Mapping[str, float], channels: Sequence[str], band_hz: float,
                        rig: Mapping[str, float] | None = None):
    """The measurement in ``path``, read and checked as the workflow does before a diagnosis (:func:`newdyn.io.
    read_measurement`, :func:`newdyn.measurement_checks.check_measurement`, its channels' levels against the ``rig``'s
    where given); a bad one raises :class:`newdyn.io.MeasurementError`."""
    from . import io, measurement_checks

    measurement = io.read_measurement(path, operating)
    values = None if rig is None else {**rig, **measurement.operating}
    measurement_checks.check_measurement(measurement, channels, band_hz, path, values=values)
    return measurement


def name_problem(path: str | os.PathLike, name: str) -> str | None:
    """The line refusing the measurement ``path`` for its ``name`` (``<recording>`` or ``<machine>/<recording>``), if
    the name holds what a file or folder name of the measurements may not, or a recording of a machine takes the name
    of one of the machine's own result folders."""
    parts = name.split("/")
    if not all(NAME.fullmatch(part) for part in parts):
        return f"{path}: names of files and folders may hold letters, digits, '_', '-' and '.' only"
    if len(parts) == 2 and parts[1] in MACHINE_FOLDERS:
        return (f"{path}: a machine's recording may not be named '{parts[1]}', the name of the machine's own results "
                f"folder results/diagnosis/{parts[0]}/{parts[1]}; rename the file")
    return None


def _problem(path: Path, operating, channels, band_hz, rig) -> str | None:
    from . import io

    try:
        checked_measurement(path, operating, channels, band_hz, rig)
    except io.MeasurementError as error:
        return str(error)
    return None


def machines(good: Mapping[str, str]) -> dict[str, list[str]]:
    """Machine name → the names of its good recordings (``<machine>/<recording>``), from :func:`good_measurements`."""
    found: dict[str, list[str]] = {}
    for name in sorted(good):
        if "/" in name:
            found.setdefault(name.split("/")[0], []).append(name)
    return found
