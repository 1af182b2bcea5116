"""What produced a result: package and dependency versions, and a hash of the science code.

Snakemake reruns a job when its rule text or params change but cannot see the modules a rule
imports; passing :func:`source_hash` of those modules as a param makes a model edit rerun exactly
the jobs that depend on it.  Kept free of heavy imports: the Snakefile imports it.
"""

from __future__ import annotations

import hashlib
import json
import platform
from collections.abc import Sequence
from importlib import metadata
from importlib.util import find_spec
from pathlib import Path

_DEPENDENCIES = ("numpy", "scipy", "numba", "xarray", "netCDF4")


def source_hash(*modules: str, files: Sequence[str] = (), packages: Sequence[str] = ()) -> str:
    """SHA-256 (first 16 hex digits) over the source files of ``newdyn.<module>`` for each module, of every
    module of ``newdyn.<package>`` for each package (its subpackages too) and over ``files`` (e.g. the
    files of the effects a job simulates)."""
    digest = hashlib.sha256()
    origins = []
    for name in sorted(modules):
        spec = find_spec(f"newdyn.{name}")
        if spec is None or spec.origin is None:
            raise ModuleNotFoundError(f"newdyn.{name}")
        origins.append((name, spec.origin))
    for name in sorted(packages):
        spec = find_spec(f"newdyn.{name}")
        if spec is None or not spec.submodule_search_locations:
            raise ModuleNotFoundError(f"newdyn.{name} (a package)")
        folder = Path(spec.origin).parent
        origins += [(f"{name}/{path.relative_to(folder).as_posix()}", str(path)) for path in sorted(folder.rglob("*.py"))]
    for name, path in origins + [(Path(path).name, path) for path in files]:
        with open(path, "rb") as source:
            digest.update(name.encode() + b"\0" + source.read())
    return digest.hexdigest()[:16]


def attributes(code_hash: str, hash_key: str = "code_hash") -> dict[str, str]:
    """The provenance attributes every output file carries: the hash of the code that made it and
    the versions (as JSON text, which netCDF accepts)."""
    found = versions()
    return {hash_key: code_hash, "newdyn_version": found["newdyn"], "versions": json.dumps(found, sort_keys=True)}


def versions() -> dict[str, str]:
    """Versions of newdyn, Python and the numerical dependencies, for file attributes."""
    found = {"python": platform.python_version()}
    for package in ("newdyn", *_DEPENDENCIES):
        try:
            found[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            found[package] = "not installed"
    return found
