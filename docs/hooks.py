"""MkDocs hooks of the documentation site (mkdocs.yml names this file).

Some user documentation lives beside what it documents, outside ``docs/``: the configuration reference in
``config/README.md``, the guide to writing an effect in ``effects/README.md`` and the changelog.  The site takes
them in as pages of their own (:data:`INCLUDED`), so they are written once and read both on the repository and
on the site.  Their links, and the links of the pages in ``docs/`` to them, are written as paths in the
repository (``../config/README.md``): :func:`on_page_markdown` turns every link that reaches a page of the site
into the path between the two pages there, and leaves any other link alone for MkDocs to check.  Headings get
the anchors the repository's web view gives them (:func:`github_slug`), so one ``#anchor`` works in both.
"""

from __future__ import annotations

import ast
import itertools
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
DOCS = "docs"
# repository path -> the page's path on the site
INCLUDED = {"config/README.md": "configuration.md", "effects/README.md": "effects.md", "CHANGELOG.md": "changelog.md"}
_FENCE = re.compile(r"^(```|~~~)")
_LINK = re.compile(r"(\]\()([^)\s]+)((?:\s+\"[^\"]*\")?\))")


def github_slug(value: str, separator: str = "-") -> str:
    """A heading's anchor as the repository's web view makes it: lower case, punctuation dropped, each space a
    hyphen (so "`effects` — the study's own effects" is ``effects--the-studys-own-effects``)."""
    return re.sub(r"[^\w\- ]", "", value.strip().lower()).replace(" ", separator)


def on_config(config):
    config.mdx_configs.setdefault("toc", {})["slugify"] = github_slug
    return config


def on_files(files, config):
    for repository_path, page in INCLUDED.items():
        files.append(File.generated(config, page, abs_src_path=str(ROOT / repository_path)))
    return files


def on_page_markdown(markdown, page, config, files):
    """The page's links to pages of the site as paths on the site (outside fenced code)."""
    where = _repository_path(page.file.src_uri)
    markdown = generated(markdown)
    lines, fenced = [], False
    for line in markdown.splitlines(keepends=True):
        if _FENCE.match(line.lstrip()):
            fenced = not fenced
        lines.append(line if fenced else _LINK.sub(lambda link: _relinked(link, where, page.file.src_uri), line))
    return "".join(lines)


def _repository_path(site_path: str) -> str:
    """Where the page of ``site_path`` lives in the repository."""
    return next((repository for repository, page in INCLUDED.items() if page == site_path), f"{DOCS}/{site_path}")


def _site_path(repository_path: str) -> str | None:
    """The site's path of a file of the repository, or None when the site does not hold it."""
    if repository_path in INCLUDED:
        return INCLUDED[repository_path]
    if repository_path.startswith(f"{DOCS}/") and repository_path.endswith(".md"):
        return repository_path[len(DOCS) + 1:]
    return None


def _relinked(link: re.Match, where: str, site_path: str) -> str:
    target, anchor = (link[2].split("#", 1) + [""])[:2]
    if not target or "://" in target or target.startswith(("/", "mailto:")):
        return link[0]
    on_site = _site_path(posixpath.normpath(posixpath.join(posixpath.dirname(where), target)))
    if on_site is None:
        return link[0]
    relative = posixpath.relpath(on_site, posixpath.dirname(site_path) or ".")
    return f"{link[1]}{relative}{'#' + anchor if anchor else ''}{link[3]}"


# --- The contributor's map (docs/architecture.md): its tables are read from the code each time the site is built,
# so they cannot go stale.  A line `<!-- generated: <table> -->` of that page is replaced by the table.

PACKAGE = ROOT / "src" / "newdyn"
RULES = ROOT / "workflow" / "rules"
# Folders whose files are one extension point each: the map shows the folder as one module.
FOLDERS = ("effects.library", "discovery.forms")
LARGE = 600  # lines: a module above this is listed as large
_MARKER = re.compile(r"^<!-- generated: (\w+) -->$", re.MULTILINE)


def _module_name(path: Path) -> str:
    """``newdyn.<name>`` of a source file as the map names it (without ``newdyn.``; the package itself is ``newdyn``)."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts) or "newdyn"
    return next((folder for folder in FOLDERS if name.startswith(folder + ".")), name)


def package_modules() -> dict[str, list[Path]]:
    """Every module of the package (a folder of :data:`FOLDERS` as one) and its source files."""
    modules: dict[str, list[Path]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        modules.setdefault(_module_name(path), []).append(path)
    return modules


def _imports(path: Path, known: dict) -> tuple[set[str], set[str]]:
    """The package's modules that ``path`` imports when it is imported, and those it imports only inside functions."""
    package = list(path.relative_to(PACKAGE).parent.parts)

    def module(parts: list[str]) -> str | None:  # the longest prefix of ``parts`` that is a module of the map
        for end in range(len(parts), -1, -1):
            name = ".".join(parts[:end]) or "newdyn"
            name = next((folder for folder in FOLDERS if name.startswith(folder + ".")), name)
            if name in known:
                return name
        return None

    at_import, in_functions = set(), set()

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            targets = []
            if isinstance(child, ast.Import):
                targets = [alias.name.split(".")[1:] for alias in child.names if alias.name.split(".")[0] == "newdyn"]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package[: len(package) - child.level + 1] + (child.module.split(".") if child.module else [])
                    targets = [[*base, alias.name] for alias in child.names]
                elif child.module and child.module.split(".")[0] == "newdyn":
                    targets = [[*child.module.split(".")[1:], alias.name] for alias in child.names]
            for target in targets:
                if (found := module(target)) is not None:
                    (in_functions if inside else at_import).add(found)
            visit(child, inside)

    visit(ast.parse(path.read_bytes(), filename=str(path)), False)
    return at_import, in_functions


def import_graph() -> dict[str, tuple[set[str], set[str]]]:
    """Each module -> (the modules it imports when imported, those it imports only inside functions)."""
    modules = package_modules()
    graph = {}
    for name, paths in modules.items():
        at_import, in_functions = set(), set()
        for path in paths:
            now, later = _imports(path, modules)
            at_import |= now
            in_functions |= later
        graph[name] = (at_import - {name}, in_functions - at_import - {name})
    return graph


def cycles(graph) -> list[list[str]]:
    """The groups of modules that import one another round (strongly connected components of more than one), each
    sorted, by Tarjan's algorithm."""
    edges = {name: sorted(now | later) for name, (now, later) in graph.items()}
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def connect(name: str) -> None:
        index[name] = low[name] = len(index)
        stack.append(name)
        on_stack.add(name)
        for other in edges[name]:
            if other not in index:
                connect(other)
                low[name] = min(low[name], low[other])
            elif other in on_stack:
                low[name] = min(low[name], index[other])
        if low[name] == index[name]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == name:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for name in sorted(edges):
        if name not in index:
            connect(name)
    return sorted(found)


def _shortest_round(graph, start: str, group: set[str]) -> list[str]:
    """The shortest path of imports inside ``group`` from ``start`` back to it (breadth first), both ends included."""
    paths, seen = [[start]], {start}
    while paths:
        path = paths.pop(0)
        for other in sorted(graph[path[-1]][0] | graph[path[-1]][1]):
            if other == start:
                return [*path, start]
            if other in group and other not in seen:
                seen.add(other)
                paths.append([*path, other])
    return [start]


def floors(graph) -> dict[str, int]:
    """Each module's floor: 0 when it imports nothing of the package, else one above the highest it imports (imports
    inside functions count; the modules of one cycle share a floor)."""
    group_of = {member: tuple(group) for group in cycles(graph) for member in group}
    floor: dict[str, int] = {}

    def level(name: str) -> int:
        if name not in floor:
            group = group_of.get(name, (name,))
            for member in group:
                floor[member] = 0  # while its imports are being climbed: a cycle does not recurse forever
            below = {other for member in group for other in graph[member][0] | graph[member][1]} - set(group)
            height = 1 + max(map(level, below)) if below else 0
            for member in group:
                floor[member] = height
        return floor[name]

    for name in graph:
        level(name)
    return floor


def _summary(paths: list[Path]) -> str:
    """A module's one responsibility: the first sentence of its docstring (the folder's ``__init__`` for a folder),
    with reStructuredText roles as code."""
    path = next((p for p in paths if p.name == "__init__.py"), paths[0])
    text = " ".join((ast.get_docstring(ast.parse(path.read_bytes())) or "").split("\n\n")[0].split())
    text = re.split(r"(?<=[.!?])\s+(?=[A-Z])", text)[0]
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text).replace("``", "`")
    if len(paths) > 1:  # a folder: name its files
        text += " Its files: " + ", ".join(f"`{p.stem}`" for p in paths if p.name != "__init__.py") + "."
    return text.strip().replace("|", "\\|")


def _source_files(name: str, paths: list[Path]) -> str:
    relative = [p.relative_to(ROOT).as_posix() for p in paths]
    if name in FOLDERS:
        return f"`{relative[0].rsplit('/', 1)[0]}/` ({len(paths) - 1} files)"
    return f"`{relative[0]}`"


def modules_table() -> str:
    """The package's modules floor by floor, the highest first: responsibility, lines and what each imports."""
    modules, graph = package_modules(), import_graph()
    floor = floors(graph)
    rows = ["| floor | module | its one responsibility (its docstring) | lines | imports (*inside functions only*) |",
            "|---|---|---|---|---|"]
    for name in sorted(graph, key=lambda n: (-floor[n], n)):
        now, later = graph[name]
        imports = ", ".join([f"`{m}`" for m in sorted(now)] + [f"*`{m}`*" for m in sorted(later)]) or "–"
        lines = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in modules[name])
        rows.append(f"| {floor[name]} | {_source_files(name, modules[name])} | {_summary(modules[name])} | {lines} | {imports} |")
    return "\n".join(rows)


def untidy_list() -> str:
    """What the map shows as untidy today: import cycles and modules above :data:`LARGE` lines."""
    modules, graph = package_modules(), import_graph()
    items = []
    for group in cycles(graph):
        rounds = []
        for start in group:
            path = _shortest_round(graph, start, set(group))
            if not any(set(itertools.pairwise(path)) == set(itertools.pairwise(other)) for other in rounds):
                rounds.append(path)
        said = ["".join(f"`{a}` → " + ("" if b in graph[a][0] else "*(inside a function)* ") for a, b in itertools.pairwise(path))
                + f"`{path[-1]}`" for path in rounds]
        items.append(f"- **Import cycle**: {'; '.join(said)}.")
    for name, paths in sorted(modules.items()):
        lines = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in paths)
        if name not in FOLDERS and lines > LARGE:
            items.append(f"- **Large module**: {_source_files(name, paths)}, {lines} lines.")
    return "\n".join(items) or "- Nothing: no import cycle, no module above {LARGE} lines."


def _commands() -> dict[str, str]:
    """``newdyn``'s subcommands and their help, read from ``src/newdyn/cli.py``."""
    found = {}
    for node in ast.walk(ast.parse((PACKAGE / "cli.py").read_bytes())):
        if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            function = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if function in ("command", "add_parser"):
                help_text = next((k.value.value for k in node.keywords if k.arg == "help" and isinstance(k.value, ast.Constant)),
                                 node.args[1].value if len(node.args) > 1 and isinstance(node.args[1], ast.Constant) else "")
                found[node.args[0].value] = help_text
    return found


def stages_table() -> str:
    """Each rule file's rules and the ``newdyn`` command each one runs, with that command's help."""
    commands = _commands()
    rows = ["| rule file | rule | runs | what the command does |", "|---|---|---|---|"]
    for path in sorted(RULES.glob("*.smk")):
        rule, text = None, path.read_text(encoding="utf-8")
        for line in text.splitlines():
            if found := re.match(r"rule (\w+):", line):
                rule = found[1]
            elif rule and (command := re.search(r"\bnewdyn ([a-z][a-z-]*)", line)) and command[1] in commands:
                rows.append(f"| `{path.relative_to(ROOT).as_posix()}` | `{rule}` | `newdyn {command[1]}` | {commands[command[1]]} |")
                rule = None
    return "\n".join(rows)


GENERATED = {"stages": stages_table, "modules": modules_table, "untidy": untidy_list}


def generated(markdown: str) -> str:
    """``markdown`` with each ``<!-- generated: <name> -->`` line replaced by that table of :data:`GENERATED`."""
    return _MARKER.sub(lambda marker: GENERATED[marker[1]](), markdown)


if __name__ == "__main__":  # python docs/hooks.py: the generated tables, to read them without building the site
    for name, make in GENERATED.items():
        print(f"<!-- {name} -->\n{make()}\n")
