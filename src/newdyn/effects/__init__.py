"""Physical effects: one file each, behind the one interface of :mod:`newdyn.effects.base`.

The built-in library lives in ``newdyn/effects/library/``; a study adds its own from the folder
``effects/`` beside ``config/`` by naming them in the config (``effects: [name, ...]``).  Whatever
file an effect comes from, it is simulated, calibrated, diagnosed and drawn in blind tests alike.

The effects a process works with are :func:`active`: the built-ins, plus what :func:`use` added.
Every list of kinds (config schema, hidden-set classes, hypotheses, tests) is derived from it.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

from .base import PLACES, TORSIONAL_BODIES, Effect, Kinematics, Parameter, RigValues, kernel_function, shaft_angle, sincos
from .check import problems

__all__ = ["PLACES", "TORSIONAL_BODIES", "USER_FOLDER", "Effect", "EffectError", "Kinematics", "Parameter", "RigValues",
           "active", "alone", "builtin", "including", "kernel_function", "load_file", "loaded", "shaft_angle", "sincos", "use"]

LIBRARY = Path(__file__).resolve().parent / "library"
#: Where a study's own effects live, relative to the directory Snakemake runs in.
USER_FOLDER = Path("effects")


class EffectError(ValueError):
    """A bad effect file, reported as one line ``<file>: <problem>``."""

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.source}: {self.problem}")


def _module_name(path: Path) -> str:
    if path.parent == LIBRARY:
        return f"newdyn.effects.library.{path.stem}"
    digest = hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:12]
    return f"newdyn_user_effects_{digest}.{path.stem}"


_LOADED: dict[str, tuple[tuple, type[Effect]]] = {}


def load_file(path: str | Path) -> type[Effect]:
    """The effect declared in ``path``, checked (:func:`newdyn.effects.check.problems`); raises
    :class:`EffectError` with one line naming the file and its first problem.  A file is read again
    when it changed."""
    path = Path(path)
    if not path.is_file():
        raise EffectError(path, "no such file")
    stamp = (path.stat().st_mtime_ns, path.stat().st_size)
    key = str(path.resolve())
    if key in _LOADED and _LOADED[key][0] == stamp:
        return _LOADED[key][1]
    content = path.read_bytes()
    try:
        compile(content.decode("utf-8"), str(path), "exec")
    except SyntaxError as error:
        raise EffectError(path, f"syntax error on line {error.lineno}: {error.msg}") from None
    name = _module_name(path)
    if path.parent == LIBRARY:
        module = importlib.import_module(name)
    else:
        package = name.rpartition(".")[0]
        if package not in sys.modules:  # a namespace for the folder, so that the module has a home
            sys.modules[package] = importlib.util.module_from_spec(importlib.machinery.ModuleSpec(package, None, is_package=True))
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except Exception as error:  # noqa: BLE001 - a user's file may fail in any way; say how, in one line
            del sys.modules[name]
            raise EffectError(path, f"cannot be imported: {type(error).__name__}: {error}") from None
    declared = [obj for obj in vars(module).values()
                if inspect.isclass(obj) and issubclass(obj, Effect) and obj is not Effect and obj.__module__ == module.__name__]
    if len(declared) != 1:
        raise EffectError(path, f"must declare exactly one subclass of newdyn.effects.Effect (found {len(declared)})")
    effect = declared[0]
    effect.source = key
    effect.content_hash = hashlib.sha256(content).hexdigest()
    for problem in problems(effect, path.stem):
        raise EffectError(path, problem)
    _LOADED[key] = (stamp, effect)
    return effect


def loaded(content_hash: str) -> type[Effect]:
    """The loaded effect whose file had the content hash ``content_hash``.  Compiled kernels bind their
    effects this way, not by path, so a copy of a file elsewhere (another study) shares their machine code."""
    for _, effect in _LOADED.values():
        if effect.content_hash == content_hash:
            return effect
    raise LookupError(f"no loaded effect file has content hash {content_hash}")


def builtin() -> dict[str, type[Effect]]:
    """The built-in library, by name."""
    effects = [load_file(path) for path in sorted(LIBRARY.glob("*.py")) if not path.name.startswith("_")]
    return {effect.name: effect for effect in effects}


_ACTIVE: dict[str, type[Effect]] = {}


def active() -> Mapping[str, type[Effect]]:
    """The effects this process simulates: the built-ins, then the user's from :func:`use`, in that order."""
    if not _ACTIVE:
        _ACTIVE.update(builtin())
    return _ACTIVE


def use(names: Sequence[str] = (), folder: str | Path = USER_FOLDER) -> Mapping[str, type[Effect]]:
    """Make the built-ins and the user's effects ``names`` (files ``<folder>/<name>.py``) the active set."""
    chosen = builtin()
    for name in names:
        path = Path(folder) / f"{name}.py"
        if name in chosen:
            raise EffectError(path, f"'{name}' is a built-in effect; give yours another name")
        chosen[name] = load_file(path)
    _ACTIVE.clear()
    _ACTIVE.update(chosen)
    return _ACTIVE


@contextmanager
def including(path: str | Path) -> Iterator[type[Effect]]:
    """The active set with the effect of the file ``path`` added, inside a with-block; as before after it."""
    effect = load_file(path)
    if effect.name in active():
        raise EffectError(path, f"'{effect.name}' is already active")
    with _active_inside({**active(), effect.name: effect}):
        yield effect


@contextmanager
def alone(paths: Sequence[str | Path]) -> Iterator[list[type[Effect]]]:
    """The effects of the files ``paths`` as the whole active set, no built-in and none of the user's, inside a
    with-block; as before after it.  A model in which no library effect takes part (a found term on the healthy or a
    drifted rig) then runs in a kernel of those effects alone, which compiles sooner than one that also holds the library."""
    loaded = [load_file(path) for path in paths]
    if not loaded:
        raise ValueError("alone() needs at least one effect file")
    with _active_inside({effect.name: effect for effect in loaded}):
        yield loaded


@contextmanager
def _active_inside(chosen: Mapping[str, type[Effect]]) -> Iterator[None]:
    before = dict(active())
    _ACTIVE.clear()
    _ACTIVE.update(chosen)
    try:
        yield
    finally:
        _ACTIVE.clear()
        _ACTIVE.update(before)
