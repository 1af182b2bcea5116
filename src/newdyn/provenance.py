"""What produced a result: package and dependency versions, and a hash of the science code.

Snakemake reruns a job when its rule text or params change but cannot see the modules a rule
imports; passing :func:`command_hash` of the command a rule runs as a param makes an edit of any module
that command imports, directly or through others, rerun exactly the jobs that depend on it.  The imports
are read from the sources (the package's own import graph), nothing is imported: the Snakefile imports this.
Reading the graph parses every module; its answers are remembered in the cache folder under a hash of the
package's files, so that a parse of the Snakefile (on a cluster: every job's) reads the package's bytes only.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import platform
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

from . import cache

_DEPENDENCIES = ("numpy", "scipy", "numba", "xarray", "netCDF4")
PACKAGE = Path(__file__).resolve().parent
ROOT = "__init__"  # the package's own __init__, as a module name here


def source_hash(*modules: str, files: Sequence[str] = ()) -> str:
    """SHA-256 (first 16 hex digits) over the source files of ``newdyn.<module>`` for each module and over
    ``files`` (e.g. the files of the effects a job simulates)."""
    digest = hashlib.sha256()
    for name, path in [(name, _source(name)) for name in sorted(set(modules))] + [(Path(p).name, Path(p)) for p in files]:
        if path is None:
            raise ModuleNotFoundError(f"newdyn.{name}")
        digest.update(name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def command_hash(command: str, files: Sequence[str] = ()) -> str:
    """:func:`source_hash` of what ``newdyn <command>`` executes with the effect ``files`` it loads: the cli module
    and every module that the command's function, the cli functions it calls and those files import (:func:`imported`)."""
    key = hashlib.sha256(json.dumps([command, *[[str(Path(p).resolve()), hashlib.sha256(Path(p).read_bytes()).hexdigest()]
                                                for p in files]]).encode()).hexdigest()
    return cache.remembered(cache.folder() / "code-hashes" / f"{package_digest()}.json", key, lambda: _command_hash(command, files))


def _command_hash(command: str, files: Sequence[str]) -> str:
    loaded = set()
    for path in map(Path, files):
        package = list(path.resolve().parent.relative_to(PACKAGE).parts) if path.resolve().is_relative_to(PACKAGE) else []
        loaded |= _imports_in(ast.parse(path.read_bytes(), filename=str(path)), package)
    return source_hash(*command_modules(command), *imported(*loaded), files=files)


@functools.cache
def package_digest() -> str:
    """A hash of this exact package: its files' names and bytes.  Answers about the package are remembered under it."""
    digest = hashlib.sha256()
    for path in sorted(PACKAGE.rglob("*.py")):
        digest.update(path.relative_to(PACKAGE).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:32]


@functools.cache
def command_modules(command: str) -> tuple[str, ...]:
    """The modules ``newdyn <command>`` runs: those its function in ``newdyn.cli`` (the one ``main`` calls when
    ``args.command == command``) and the cli functions it calls import, with ``cli`` and ``main``'s own imports."""
    tree = _tree("cli")
    functions = {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}
    dispatch = {test.comparators[0].value: branch.body[0].value.func.id for branch in ast.walk(functions["main"])
                if isinstance(branch, ast.If) and isinstance(test := branch.test, ast.Compare)
                and isinstance(test.left, ast.Attribute) and test.left.attr == "command"}
    if command not in dispatch:
        raise ValueError(f"newdyn has no command {command!r} (it has {', '.join(sorted(dispatch))})")
    seen, todo = set(), [dispatch[command]]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        todo += [n.func.id for n in ast.walk(functions[name])
                 if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in functions]
    roots = _imports_in(ast.Module([s for s in tree.body if not isinstance(s, ast.FunctionDef)], []), [])
    for name in seen | {"main"}:  # main's own imports: it dispatches to every command, whose imports are theirs
        roots |= _imports_in(functions[name], [])
    return tuple(sorted({"cli", *imported(*roots)}))


def imported(*roots: str) -> tuple[str, ...]:
    """``roots`` and every module of the package they import, directly or through others, at import time or
    inside functions, with the packages on the way (sorted)."""
    found, todo = set(), list(roots)
    while todo:
        name = todo.pop()
        if name in found:
            continue
        if _source(name) is None:
            raise ModuleNotFoundError(f"newdyn.{name}")
        found.add(name)
        todo += _module_imports(name)
    return tuple(sorted(found))


@functools.cache
def _module_imports(name: str) -> frozenset[str]:
    """What the source of ``newdyn.<name>`` imports (:func:`_imports_in`), read once."""
    is_package = _source(name).name == "__init__.py" and name != ROOT
    return frozenset(_imports_in(_tree(name), name.split(".") if is_package else name.split(".")[:-1]))


def _imports_in(node: ast.AST, package: list[str]) -> set[str]:
    """The package's modules that the import statements anywhere in ``node``, code of the subpackage ``package``
    ([] for newdyn itself), load."""
    found = set()
    for n in ast.walk(node):
        if isinstance(n, ast.Import):
            names = [alias.name.split(".")[1:] for alias in n.names if alias.name.split(".")[0] == "newdyn"]
            found |= {".".join(parts[:i]) or ROOT for parts in names for i in range(len(parts) + 1)}
        elif isinstance(n, ast.ImportFrom):
            if n.level:
                base = package[: len(package) - n.level + 1] + (n.module.split(".") if n.module else [])
            elif n.module and n.module.split(".")[0] == "newdyn":
                base = n.module.split(".")[1:]
            else:
                continue
            found |= {".".join(base[:i]) or ROOT for i in range(len(base) + 1)}
            found |= {".".join([*base, alias.name]) for alias in n.names if _source(".".join([*base, alias.name]))}
        elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "with_name" and n.args
              and isinstance(n.args[0], ast.Constant) and str(n.args[0].value).endswith(".py")):
            found.add(".".join([*package, str(n.args[0].value).removesuffix(".py")]))  # a module whose source it reads
        elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "iter_modules" and n.args
              and isinstance(n.args[0], ast.Name) and n.args[0].id == "__path__"):  # a registry: it loads all its modules
            found |= {".".join([*package, path.stem]) for path in PACKAGE.joinpath(*package).glob("*.py") if path.stem != "__init__"}
    return found


@functools.cache
def _source(module: str) -> Path | None:
    """The file of ``newdyn.<module>`` (:data:`ROOT`: the package's ``__init__``), None when there is none."""
    base = PACKAGE.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


@functools.cache
def _tree(module: str) -> ast.Module:
    return ast.parse(_source(module).read_bytes(), filename=str(_source(module)))


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
