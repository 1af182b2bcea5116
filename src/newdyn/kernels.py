"""The batched simulation kernel, compiled once per set of effects.

``kernel_template.py`` holds the kernel of the healthy rig (RK4, event location, lanes, threads);
:func:`module` renders it for the active effects (:mod:`newdyn.effects`): their parameter slots and
mode rows, and straight-line code that adds each effect's force at its place, evaluates its event
function and applies its switch.  The rendered module is written under the cache folder
(``NEWDYN_CACHE``, default ``~/.cache/newdyn``) with a name that hashes the template, the effects'
files and numba's version, so numba caches its machine code beside it: an effect set compiles
once, and an edit of an effect file compiles anew.  Processes that need a kernel not compiled yet share
its compile, part by part (:func:`compile_parts`).
"""

from __future__ import annotations

import ast
import fcntl
import hashlib
import importlib.util
import inspect
import itertools
import os
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

import numba
import numpy as np
from numba import get_num_threads

from . import cache, effects, model, slots

TEMPLATE = Path(__file__).with_name("kernel_template.py")

# Output codes: 0 .. len(model.CHANNELS) - 1 are model.CHANNELS in order (the template's _record computes each);
# then the slip joint's locked torque (the T_f of Eq. 3b); then per switching effect j its mode (OUT_MODES + j) and
# its number of onsets (switches out of mode 0, OUT_MODES + N_SWITCHING + j); OUT_STATE + i is state component i.
OUT_TORQUE_C = model.CHANNELS.index("torque_c")
OUT_JOINT_TORQUE = len(model.CHANNELS)
OUT_MODES = OUT_JOINT_TORQUE + 1
OUT_STATE = 100

# The element torque of the kernel that a torsional place's force is added to, with which sign.
_TORSIONAL = {
    "motor": ("torque1", "+"),
    "motor_shaft": ("t_s1", "-"),
    "slip_joint": ("f_joint", "+"),
    "coupling": ("t_c", "+"),
    "load_shaft": ("t_s3", "+"),
    "load": ("torque4", "+"),
}


def _coordinate(place: str, src: str) -> tuple[str, str, str]:
    """(x, v, accumulator) expressions of a place at state rows ``src`` (the angles lead the state)."""
    if place in _TORSIONAL:
        a, b = (None if body is None else model.ANGLES.index(body) for body in effects.TORSIONAL_BODIES[place])
        x = f"w[_at({src} + {a}, lane)]" + (f" - w[_at({src} + {b}, lane)]" if b is not None else "")
        v = f"w[_at({src} + NQ + {a}, lane)]" + (f" - w[_at({src} + NQ + {b}, lane)]" if b is not None else "")
        return x, v, _TORSIONAL[place][0]
    node, _, axis = place.partition("_")
    row = (5 if axis == "x" else 13) + model.NODES.index(node)
    return f"w[_at({src} + {row}, lane)]", f"w[_at({src} + NQ + {row}, lane)]", f"f{axis}{model.NODES.index(node)}"


def _reads(function, argument: int) -> set[str] | None:
    """The attributes ``function`` reads of its argument number ``argument``; None if it hands the
    argument on whole (then anything may be read)."""
    definition = ast.parse(textwrap.dedent(inspect.getsource(function))).body[0]
    name = definition.args.args[argument].arg
    uses = [node for node in ast.walk(definition) if isinstance(node, ast.Name) and node.id == name]
    attributes = [node.attr for node in ast.walk(definition)
                  if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == name]
    return set(attributes) if len(uses) == len(attributes) else None


def rig_fields(effect: type[effects.Effect]) -> tuple[str, ...]:
    """The rig values an effect's functions read (``rig.<name>``); all of them if one hands ``rig`` on.

    Each effect gets a rig tuple of just these: LLVM then has less to prove dead, which shortens the
    kernel's compile time against one tuple of every rig value."""
    used: set[str] = set()
    for function in (effect.force, effect.event, effect.switch):
        if function is not None:
            reads = _reads(function, 2)
            if reads is None:
                return effects.base.RIG_FIELDS
            used |= reads
    return tuple(name for name in effects.base.RIG_FIELDS if name in used)


def force_reads_joint_torque(effect: type[effects.Effect]) -> bool:
    """Whether an effect's force reads ``s.joint_torque``.  The right-hand side computes that torque
    only for such a force: computed on every evaluation it made a lone simulation 6x slower."""
    reads = _reads(effect.force, 0)
    return reads is None or "joint_torque" in reads


def dense_rows(active: dict[str, type[effects.Effect]]) -> list[int]:
    """Position rows the switching effects' event functions read: the torsional ones (angles, twists,
    the slip joint's torque) and the lateral node each acts on."""
    rows = list(range(5))
    for effect in active.values():
        if effect.switching() and effect.acts_on not in _TORSIONAL:
            node, _, axis = effect.acts_on.partition("_")
            rows.append((5 if axis == "x" else 13) + model.NODES.index(node))
    return sorted(set(rows))


def render(active: dict[str, type[effects.Effect]]) -> str:
    """The kernel module's source for the effects ``active`` (name -> effect), in their order."""
    index = slots.slot_index()
    switching = [kind for kind, effect in active.items() if effect.switching()]
    layout = [
        "# Generated by newdyn.kernels for the effects " + (", ".join(active) or "(none)") + ": do not edit.",
        f"_I = {dict(model.PARAMETER_INDEX)!r}",
        f"N_PAR = {len(index)}",
        f"N_SWITCHING = {len(switching)}",
        f"SWITCHING_ON = np.array({[index[slots.effect_slot(kind)] for kind in switching]!r}, dtype=np.int64)",
        f"DENSE_ROWS = np.array({dense_rows(active)!r}, dtype=np.int64)",
        f"OUT_TORQUE_C, OUT_JOINT_TORQUE, OUT_MODES, OUT_STATE = {OUT_TORQUE_C}, {OUT_JOINT_TORQUE}, {OUT_MODES}, {OUT_STATE}",
    ]
    for i, (kind, effect) in enumerate(active.items()):
        names = tuple(p.name for p in effect.kernel_parameters()) or ("unused",)
        layout += [
            f"_EFFECT_{i} = loaded({effect.content_hash!r})  # {kind}",
            f"_force_{i} = njit(**_EFFECT_JIT)(kernel_ready(_EFFECT_{i}.force))",
            f"_P{i} = namedtuple('_P{i}', {names!r})",
            f"_R{i} = namedtuple('_R{i}', {rig_fields(effect) or ('unused',)!r})",
        ]
        if effect.switching():
            layout += [f"_event_{i} = njit(**_EFFECT_JIT)(kernel_ready(_EFFECT_{i}.event))",
                       f"_switch_{i} = njit(**_EFFECT_JIT)(kernel_ready(_EFFECT_{i}.switch))"]
    source = TEMPLATE.read_text(encoding="utf-8").replace("# @layout@", "\n".join(layout))
    return _index_written_out(source + "\n\n" + _generated(active, index, switching))


def _index_written_out(source: str) -> str:
    """``source`` with each ``_at(row, lane)`` written out as the flat index it stands for, np.uint64((row) * LANES +
    (lane)).  As a function numba inlines, each of its hundreds of calls cost the compile a copy of its IR and a type
    inference; written out, LLVM gets the same code."""
    lines = source.splitlines(keepends=True)
    starts = [0, *itertools.accumulate(len(line) for line in lines)]

    def offset(line: int, byte: int) -> int:  # ast's columns count UTF-8 bytes
        return starts[line - 1] + len(lines[line - 1].encode("utf-8")[:byte].decode("utf-8"))

    def outermost(node):  # the calls of _at that are not inside another one's arguments
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "_at":
            yield node
        else:
            for child in ast.iter_child_nodes(node):
                yield from outermost(child)

    def text(node: ast.AST) -> str:  # as ast.get_source_segment, which splits the whole source into lines at each call
        return source[offset(node.lineno, node.col_offset):offset(node.end_lineno, node.end_col_offset)]

    def written_out(argument: ast.AST) -> str:  # in brackets, so that an argument spanning lines parses on its own
        inner = text(argument)
        return _index_written_out(f"({inner})")[1:-1] if "_at(" in inner else inner

    edits = []
    for call in outermost(ast.parse(source)):
        row, lane = (written_out(argument) for argument in call.args)
        edits.append((offset(call.lineno, call.col_offset), offset(call.end_lineno, call.end_col_offset),
                      f"np.uint64(({row}) * LANES + ({lane}))"))
    for start, end, written in sorted(edits, reverse=True):
        source = source[:start] + written + source[end:]
    return source


def _parameters(i: int, effect, index: dict[str, int]) -> str:
    columns = [index[slots.effect_slot(effect.name, p.name)] for p in effect.kernel_parameters()]
    return f"_P{i}(" + ", ".join(f"w[_at({column}, lane)]" for column in columns) + ")" if columns else f"_P{i}(0.0)"


def _rig(i: int, effect) -> str:
    rows = {name: f"w[_at({row}, lane)]" for row, name in enumerate(model.PARAMETER_NAMES)} | {"Omega": "w[_at(R_OMEGA, lane)]"}
    return f"_R{i}(" + ", ".join(rows[name] for name in rig_fields(effect) or ("Omega",)) + ")"


def _mode(kind: str, switching: list[str]) -> str:
    return f"w[_at(R_MODES + {switching.index(kind)}, lane)]" if kind in switching else "0.0"


def _kinematics(place: str, src: str, joint_torque: str) -> str:
    """A Kinematics of ``place`` at state rows ``src``; its joint torque is the expression ``joint_torque``
    on the slip joint (0 elsewhere)."""
    x, v, _ = _coordinate(place, src)
    return (f"Kinematics(t, {x}, {v}, w[_at({src}, lane)], w[_at({src} + 4, lane)], w[_at({src} + NQ, lane)], "
            f"w[_at({src} + NQ + 4, lane)], {joint_torque if place == 'slip_joint' else '0.0'})")


def _effect_lines(i: int, kind: str, effect, index, switching, src: str) -> list[str]:
    """Code that adds effect i's force at its place (to the local accumulator of that place)."""
    _, _, target = _coordinate(effect.acts_on, src)
    sign = _TORSIONAL[effect.acts_on][1] if effect.acts_on in _TORSIONAL else "+"
    present = f"w[_at({index[slots.effect_slot(kind)]}, lane)] != 0.0"
    lines = [
        f"    # {kind} on {effect.acts_on}",
        f"    mode_{i} = {_mode(kind, switching)}",
        (f"    force_{i} = _force_{i}({_kinematics(effect.acts_on, src, 'joint_torque' if force_reads_joint_torque(effect) else '0.0')}, "
         f"{_parameters(i, effect, index)}, {_rig(i, effect)}, mode_{i})"),
    ]
    if effect.acts_on == "slip_joint":
        return lines + [f"    open_{i} = {_opens_joint(i, kind, effect, index, switching)}",
                        f"    f_joint = f_joint + force_{i} if open_{i} else f_joint",
                        f"    joint_open = 1.0 if open_{i} else joint_open"]
    return lines + [f"    {target} = {target} {sign} force_{i} if {present} else {target}"]


def _opens_joint(i: int, kind: str, effect, index, switching) -> str:
    """Whether effect i, on the slip joint, holds it open: present, and a locking one out of its mode 0."""
    present = f"(w[_at({index[slots.effect_slot(kind)]}, lane)] != 0.0)"
    return f"{present} & ({_mode(kind, switching)} != 0.0)" if effect.locks_joint else present


def _generated(active, index, switching) -> str:
    items = list(enumerate(active.items()))
    shafts = [(i, k, e) for i, (k, e) in items if e.acts_on in ("motor_shaft", "coupling")]
    others = [(i, k, e) for i, (k, e) in items if e.acts_on not in ("motor_shaft", "coupling", "slip_joint")]
    joint = [(i, k, e) for i, (k, e) in items if e.acts_on == "slip_joint"]
    lines = [
        "# --- generated from the effects -------------------------------------------------------------------",
        "@njit(**_JIT, inline='always')",
        "def _joint_torques(w, lane, src, t):",
        '    """(t_s1, t_c, T_f): the torques of shaft 1 on disk 1 and of the coupling on disk 3 with their effects',
        '    added, and the torque the slip joint carries while locked."""',
        "    t_s1, t_c = _shaft_torques(w, lane, src)",
    ]
    if shafts:
        lines.append("    joint_torque = 0.0")
    for i, kind, effect in shafts:
        lines += _effect_lines(i, kind, effect, index, switching, "src")
    lines += [
        "    return t_s1, t_c, _stick_torque(w, lane, t_s1, t_c)",
        "",
        "",
        "@njit(**_JIT, inline='always')",
        "def _forces(w, lane, src, t):",
        '    """Element torques and node forces of one lane at state rows src, time t, with every present',
        "    effect's force added at its place: (torque on disk 1, t_s1, t_c, t_s3, torque on disk 4, slip-joint",
        '    torque, 1.0 if the slip joint is open else 0.0, its locked torque, fx[8], fy[8], sin/cos θ1 + φ1, θ4 + φ4)."""',
        "    s1, c1 = sincos(w[_at(src, lane)] + w[_at(PHI1, lane)])  # the imbalances' angles",
        "    s4, c4 = sincos(w[_at(src + 4, lane)] + w[_at(PHI4, lane)])",
        "    t_s1, t_c, joint_torque = _joint_torques(w, lane, src, t)",
        "    t_s3 = _load_shaft_torque(w, lane, src)",
        "    torque1 = w[_at(T0, lane)] - w[_at(R_CM, lane)] * (w[_at(src + NQ, lane)] - w[_at(R_OMEGA, lane)])",
        "    torque4 = -w[_at(R_TL, lane)]",
        "    fx0, fx1, fx2, fx3, fx4, fx5, fx6, fx7 = _lateral(w, lane, src + 5, w[_at(KBX, lane)])",
        "    fy0, fy1, fy2, fy3, fy4, fy5, fy6, fy7 = _lateral(w, lane, src + 13, w[_at(KBY, lane)])",
        "    f_joint = 0.0",
        "    joint_open = 0.0",
    ]
    for i, kind, effect in others + joint:
        lines += _effect_lines(i, kind, effect, index, switching, "src")
    lines += [
        "    torque1 = torque1 + t_s1  # the disks' net torques, with the shafts' effects",
        "    torque4 = t_s3 + torque4",
        "    return (torque1, t_s1, t_c, t_s3, torque4, f_joint, joint_open, joint_torque, fx0, fx1, fx2, fx3, fx4, fx5, fx6, fx7,",
        "            fy0, fy1, fy2, fy3, fy4, fy5, fy6, fy7, s1, c1, s4, c4)",
        "",
        "",
        "@njit(**_JIT, inline='always')",
        "def _event_value(w, lane, src, t):",
        '    """(g, which): the largest event function of the present switching effects (j + 1), or (-inf, 0)."""',
        "    g = -math.inf",
        "    which = 0.0",
    ]
    if switching:
        lines.append("    joint_torque = _joint_torques(w, lane, src, t)[2]")
    for i, (kind, effect) in items:
        if not effect.switching():
            continue
        j = switching.index(kind)
        present = f"w[_at({index[slots.effect_slot(kind)]}, lane)] != 0.0"
        lines += [
            f"    g_{i} = _event_{i}({_kinematics(effect.acts_on, 'src', 'joint_torque')}, {_parameters(i, effect, index)}, {_rig(i, effect)}, {_mode(kind, switching)})",
            f"    first_{i} = ({present}) & (g_{i} > g)",
            f"    which = {float(j + 1)} if first_{i} else which",
            f"    g = g_{i} if first_{i} else g",
        ]
    lines += [
        "    return g, which",
        "",
        "",
        "@njit(**_JIT, inline='always')",
        "def _joint_open(w, lane):",
        '    """1.0 if a present effect holds the slip joint open, else 0.0."""',
        "    joint_open = 0.0",
        *[f"    joint_open = 1.0 if {_opens_joint(i, kind, effect, index, switching)} else joint_open" for i, kind, effect in joint],
        "    return joint_open",
        "",
        "",
        "@njit(**_JIT)",
        "def _switch_effect(w, lane, which, t):",
        '    """Switch effect ``which`` (j + 1) at the state in rows R_Y of ``lane``: its new mode, the momentum-',
        '    weighted common speed of 2a and 2b where it locks the slip joint, and its count of onsets."""',
    ]
    if switching:
        lines.append("    joint_torque = _joint_torques(w, lane, R_Y, t)[2]")
    else:
        lines.append("    return")
    for i, (kind, effect) in items:
        if not effect.switching():
            continue
        j = switching.index(kind)
        lines += [
            f"    if which == {float(j + 1)}:",
            f"        old = w[_at(R_MODES + {j}, lane)]",
            f"        new = _switch_{i}({_kinematics(effect.acts_on, 'R_Y', 'joint_torque')}, {_parameters(i, effect, index)}, {_rig(i, effect)}, old)",
            f"        w[_at(R_MODES + {j}, lane)] = new",
            "        if old == 0.0 and new != 0.0:",
            f"            w[_at(R_ONSETS + {j}, lane)] += 1.0",
        ]
        if effect.locks_joint:
            lines += [
                "        if new == 0.0 and old != 0.0:  # the joint locks: both sides take the momentum-weighted common speed",
                "            momentum = w[_at(J2A, lane)] * w[_at(R_Y + NQ + 1, lane)] + w[_at(J2B, lane)] * w[_at(R_Y + NQ + 2, lane)]",
                "            common = momentum * w[_at(R_INVJ2, lane)]",
                "            w[_at(R_Y + NQ + 1, lane)] = common",
                "            w[_at(R_Y + NQ + 2, lane)] = common",
            ]
    return "\n".join(lines) + "\n"


_MODULES: dict[str, ModuleType] = {}  # by kernel digest
_LOADED: dict[tuple, ModuleType] = {}  # by the (name, effect class) pairs of the active set


def kernel_digest(active: dict[str, type[effects.Effect]], source: str | None = None) -> str:
    """The name of the compiled kernel of the effects ``active``: a hash of its rendered source (which
    names each effect by its file's content hash, so an edited effect gets a kernel of its own, never
    the machine code that numba cached for the old one), of the effects package's own modules (the
    helpers effects call, such as ``sincos``: numba's cache does not see an edit of a callee) and of
    numba's and Python's versions."""
    shared = b"".join(path.read_bytes() for path in sorted(Path(effects.__file__).parent.glob("*.py")))
    text = (source or render(active)) + numba.__version__ + sys.version
    return hashlib.sha256(text.encode() + shared).hexdigest()[:16]


def module(active: dict[str, type[effects.Effect]] | None = None) -> ModuleType:
    """The compiled kernel module of the effects ``active`` (default: :func:`newdyn.effects.active`)."""
    active = dict(active if active is not None else effects.active())
    # Rendering parses the effects' sources (~25 ms): once per set of effect classes (a changed file
    # is a new class, see newdyn.effects.load_file), not on every simulation.
    key = tuple(active.items())
    if key in _LOADED:
        return _LOADED[key]
    source = render(active)
    digest = kernel_digest(active, source)
    if digest in _MODULES:
        _LOADED[key] = _MODULES[digest]
        return _MODULES[digest]
    path = _written(source, digest)
    compiled = _import(path)
    _compile_once(compiled, path, active)
    _MODULES[digest] = _LOADED[key] = compiled
    return compiled


def is_compiled(active: dict[str, type[effects.Effect]]) -> bool:
    """Whether the kernel of the effects ``active`` is compiled already (in this process or the cache folder)."""
    active = dict(active)
    return tuple(active.items()) in _LOADED or _path(kernel_digest(active)).with_suffix(".ready").exists()


def _path(digest: str) -> Path:
    """Where the kernel module of ``digest`` is written, numba's cache of it beside it."""
    return cache.folder() / "kernels" / f"kernel_{digest}.py"


def _written(source: str, digest: str) -> Path:
    """The file of the kernel module ``source`` named ``digest``, written unless it is there."""
    path = _path(digest)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        # Written once and never rewritten: numba's cache is keyed on the file's time stamp.
        with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False, encoding="utf-8") as f:
            f.write(source)
        try:
            os.link(f.name, path)
        except FileExistsError:
            pass  # another process wrote the same source first
        finally:
            os.unlink(f.name)
    return path


def _import(path: Path) -> ModuleType:
    """The kernel module written at ``path`` (its effects loaded in this process), imported without compiling it."""
    spec = importlib.util.spec_from_file_location(f"newdyn_{path.stem}", path)
    compiled = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = compiled
    spec.loader.exec_module(compiled)
    return compiled


def _compile_once(compiled: ModuleType, path: Path, active: dict[str, type[effects.Effect]]) -> None:
    """Compile the kernel at ``path`` into numba's cache unless it is there, sharing the work with other processes.

    Processes that start together on an empty cache (a study's first jobs, test workers) would each compile the same
    kernel, half a minute of a core apiece.  Instead each compiles the parts of it that no other has taken
    (:func:`compile_parts`), and then one compiles the entry point, loading the parts from numba's cache, while the
    others wait and load its machine code.  A process that may use a second core (numba's thread count) starts a
    helper on it that takes a part.  The entry point is compiled with the argument types :func:`_run` passes, on a
    run of no steps."""
    ready = path.with_suffix(".ready")
    if ready.exists():
        return
    helper = None
    if get_num_threads() > 1:
        sources = [effect.source for effect in active.values()]
        helper = subprocess.Popen([sys.executable, "-c", _HELPER, str(path), *sources], env={**os.environ,
                                  "NUMBA_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        compile_parts(compiled, path)
        with open(path.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not ready.exists():
                _run(compiled, np.zeros((1, compiled.N_PAR)), 0.0, 1.0, 1, 1, np.zeros(1, dtype=np.int64), {})
                ready.touch()
    finally:
        if helper is not None:  # it may still be loading a part this process compiled
            helper.kill()
            helper.wait()


def help_compile(path: str, sources: Sequence[str]) -> ModuleType:
    """What a helper process does: the kernel module at ``path`` imported with its effects loaded from their files
    ``sources``, then the parts of it that no other process has taken compiled (:func:`compile_parts`); returns the
    module."""
    for source in sources:
        effects.load_file(source)
    compiled = _import(Path(path))
    compile_parts(compiled, Path(path))
    return compiled


_HELPER = "import sys; from newdyn import kernels; kernels.help_compile(sys.argv[1], sys.argv[2:])"


def compile_parts(compiled: ModuleType, path: Path) -> None:
    """Compile into numba's cache each part of the kernel (``COMPILE_PARTS``) that no other process is compiling,
    then wait until the others have compiled theirs."""
    others = []
    for n, part in enumerate(compiled.COMPILE_PARTS):
        lock = open(path.with_suffix(f".part{n}.lock"), "w")  # noqa: SIM115 - closed once the part is compiled
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another process is compiling it
            others.append(lock)
            continue
        with lock:
            part.compile(())
    for lock in others:
        with lock:
            fcntl.flock(lock, fcntl.LOCK_EX)


def output_code(name: str, active: dict[str, type[effects.Effect]] | None = None) -> int | None:
    """The kernel's output code of a diagnostic: ``joint_torque``, ``<kind>.<mode_name>`` or ``<kind>.onsets``."""
    active = dict(active if active is not None else effects.active())
    switching = [(kind, e) for kind, e in active.items() if e.switching()]
    if name == "joint_torque":
        return OUT_JOINT_TORQUE
    for j, (kind, effect) in enumerate(switching):
        if name == f"{kind}.{effect.mode_name}":
            return OUT_MODES + j
        if name == f"{kind}.onsets":
            return OUT_MODES + len(switching) + j
    return None


def diagnostics(active: dict[str, type[effects.Effect]] | None = None) -> tuple[str, ...]:
    """Names of the diagnostic outputs of the active effects."""
    active = dict(active if active is not None else effects.active())
    switching = [(kind, e) for kind, e in active.items() if e.switching()]
    return ("joint_torque", *[f"{k}.{e.mode_name}" for k, e in switching], *[f"{k}.onsets" for k, _ in switching])



# A rig whose slip joint opens needs finer steps than the healthy rig: every slip onset (a torque drop when r_k < 1)
# and re-stick kicks the chain's fastest torsional modes, whose RK4 phase error then moves the next event.  After a
# switch of its joint a lane steps with ω_max·h at most JOINT_OMEGA_RATE·h (0.18 at the default step of 1e-4 s),
# ω_max the fastest torsional mode with the joint locked or open, until the modes the switch kicked have rung down:
# SETTLE_E_FOLDS e-folding times of the fastest mode's amplitude under the rig's stiffness-proportional damping,
# 2 / (β ω_max²) (for ever without damping).  An open joint frees the light bodies 2a and 2b (J2a alone on the motor
# shaft vibrates at ~1.2 kHz); once rung down, their motion is smooth and the lane steps with ω_open·h at most
# OPEN_OMEGA_RATE·h (0.8), ω_open the fastest mode with the joint open, for as long as it stays open: the default rig's
# slipping joint then takes the plain step once settled.  All depend on the lane's own parameters only, so halving the
# step halves it on every lane.
JOINT_OMEGA_RATE = 1800.0  # rad/s
OPEN_OMEGA_RATE = 8000.0  # rad/s
# A global search only chooses where least squares on the exact simulator starts: its slipping lanes step twice as
# long (ω_max·h ≤ 0.36 while settling, ω_open·h ≤ 1.6 while open), which keeps its searches in the truth's basin on the
# blind stick-slip cases where the plain step does not (CHANGELOG.md, 2026-11-25; re-verified 2026-11-29).
SEARCH_STEP_FACTOR = 2.0
SETTLE_E_FOLDS = 6.0
# Any other switching effect switches a contact (a wall reached or left), which kicks the rig's lateral modes with a
# jump of the contact's damping force; the lightly damped ones ring for tens of milliseconds and contacts recur at
# every vibration cycle, so such a lane takes CONTACT_STEPS steps per step from its first switch on: ω_max·h 0.28 on the
# default rig instead of the plain step's 0.57, at which a loose bearing's step halving misses rig.md's bound over part
# of its prior (docs/validation.md).
CONTACT_STEPS = 2.0


def _fastest_torsional_mode(inertias: np.ndarray, stiffnesses: np.ndarray) -> np.ndarray:
    """ω_max [rad/s] of free torsional chains, one per row: inertias (n, m), stiffnesses (n, m - 1)."""
    n, m = inertias.shape
    stiffness = np.zeros((n, m, m))
    for i in range(m - 1):
        k = stiffnesses[:, i]
        stiffness[:, i, i] += k
        stiffness[:, i + 1, i + 1] += k
        stiffness[:, i, i + 1] -= k
        stiffness[:, i + 1, i] -= k
    scale = 1.0 / np.sqrt(inertias)
    return np.sqrt(np.linalg.eigvalsh(scale[:, :, None] * stiffness * scale[:, None, :])[:, -1].clip(0.0))


def fine_steps(params: np.ndarray, active: dict[str, type[effects.Effect]] | None = None,
               search: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(RK4 steps per step (n, 2): after a switch of a row's effects for as long as it settles, and while its slip
    joint is open after that; how long it settles [s]) per row of ``params``: ceil(ω_max / JOINT_OMEGA_RATE),
    ceil(ω_open / OPEN_OMEGA_RATE) and SETTLE_E_FOLDS · 2 / (β ω_max²) where an effect on the slip joint is present,
    CONTACT_STEPS, 1 and for ever where another switching effect is (the largest where both are), else 1, 1 and 0;
    for a ``search``, SEARCH_STEP_FACTOR times fewer steps."""
    active = dict(active if active is not None else effects.active())
    index = slots.slot_index()
    joint = np.zeros(params.shape[0], dtype=bool)
    contact = np.zeros(params.shape[0], dtype=bool)
    for kind, effect in active.items():
        present = params[:, index[slots.effect_slot(kind)]] != 0.0
        if effect.acts_on == "slip_joint":
            joint |= present
        elif effect.switching():
            contact |= present
    factor = SEARCH_STEP_FACTOR if search else 1.0
    steps, settle = np.ones((params.shape[0], 2)), np.zeros(params.shape[0])
    if joint.any():
        p = {name: params[joint, index[name]] for name in ("J1", "J2a", "J2b", "J3", "J4", "kT1", "kT2", "kT3", "beta")}
        locked = _fastest_torsional_mode(np.stack([p["J1"], p["J2a"] + p["J2b"], p["J3"], p["J4"]], 1),
                                         np.stack([p["kT1"], p["kT2"], p["kT3"]], 1))
        opened = np.maximum(_fastest_torsional_mode(np.stack([p["J1"], p["J2a"]], 1), p["kT1"][:, None]),
                            _fastest_torsional_mode(np.stack([p["J2b"], p["J3"], p["J4"]], 1), np.stack([p["kT2"], p["kT3"]], 1)))
        fastest = np.maximum(locked, opened)
        steps[joint] = np.maximum(1, np.ceil(np.stack([fastest / JOINT_OMEGA_RATE, opened / OPEN_OMEGA_RATE], 1) / factor))
        with np.errstate(divide="ignore"):
            settle[joint] = SETTLE_E_FOLDS * 2.0 / (p["beta"] * fastest**2)
    steps[contact, 0] = np.maximum(steps[contact, 0], max(1.0, np.ceil(CONTACT_STEPS / factor)))
    settle[contact] = np.inf
    return steps, settle


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def blocks(n: int, n_threads: int, lanes: int, vector: int) -> tuple[np.ndarray, np.ndarray]:
    """Group n simulations into blocks of lanes: (starts, counts), block b being rows starts[b] : starts[b] + counts[b].
    Blocks of at most ``lanes`` rows, at least as many as threads while each keeps ``vector`` lanes (a narrower block
    costs as much as one of ``vector`` lanes), of equal width rounded up to ``vector``."""
    n_blocks = max(_ceil_div(n, lanes), min(n_threads, _ceil_div(n, vector)), 1)
    width = min(lanes, max(1, _ceil_div(_ceil_div(n, n_blocks), vector) * vector))
    starts = np.arange(0, n, width, dtype=np.int64)
    return starts, np.minimum(width, n - starts).astype(np.int64)


def lane_order(params: np.ndarray, steps: np.ndarray, active: dict[str, type[effects.Effect]] | None = None) -> np.ndarray:
    """The order in which the rows of ``params`` fill the blocks' lanes: by their :func:`fine_steps` counts, then by
    the parameters of the effects on the slip joint, the given order kept among equals.  A block steps its finely
    stepping lanes side by side, one step count at a time, so lanes of one count whose joints open at the same times
    (alike parameters) share blocks; a lane's result does not depend on its block."""
    active = dict(active if active is not None else effects.active())
    index = slots.slot_index()
    joint = [params[:, index[slots.effect_slot(kind, p.name)]] for kind, effect in active.items() if effect.acts_on == "slip_joint"
             for p in effect.kernel_parameters()]
    return np.lexsort((*reversed(joint), steps[:, 1], steps[:, 0])).astype(np.int64)  # lexsort's last key is its first


RIG_START = np.empty((1, 0))  # no start state given: every row starts from rig.md's


def _run(kernel: ModuleType, params: np.ndarray, t_first, fs, n_samples, substeps, codes, active=None,
         search: bool = False, states: np.ndarray | None = None) -> np.ndarray:
    # The thread count is read here: inside a compiled function it would make it uncacheable.
    starts, counts = blocks(params.shape[0], get_num_threads(), kernel.LANES, kernel.VECTOR)
    steps, settle = fine_steps(params, active, search)
    order = lane_order(params, steps, active)
    # Blocks are handed to the threads one at a time as they come free: a block of slipping lanes costs several
    # others, and the lane order puts such blocks last, where an even split would leave them to one thread.
    with numba.parallel_chunksize(1):
        return kernel._simulate_batch(params, RIG_START if states is None else states, steps, settle, order, starts, counts,
                                      substeps, t_first, fs, n_samples, codes)


def simulate_batch(params: np.ndarray, t_first, fs, n_samples, substeps, codes, search: bool = False,
                   states: np.ndarray | None = None) -> np.ndarray:
    """Simulate each row of ``params`` (n, len(slots.slot_names())); returns (n, len(codes), n_samples).

    Samples lie at t_first + k/fs; the model starts at t = 0 from each row of ``states`` (n, 42), or from the rig.md
    initial state where they are None.  Each
    sample interval takes ``substeps`` RK4 steps, times the row's :func:`fine_steps` while it settles after a switch
    or its slip joint is open (fewer for a ``search``); the warm-up up to t_first takes steps of the same length or less.
    """
    return _run(module(), params, t_first, fs, n_samples, substeps, codes, search=search, states=states)
