"""The user documentation: the site builds without a warning (so no link or anchor is broken), its tables of the
rig and of the effects are the code's, its measurement examples make files a diagnosis takes, its worked example of
an effect file is the file, and nothing sends a user to a file outside the repository.

A table of docs/rig.md that no longer matches the code fails here with the table as it must read now: paste it in.
"""

import ast
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from newdyn import effects, measurement_checks, model, noise

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def test_site_builds_strict_without_a_warning(tmp_path):
    """`mkdocs build --strict` fails on any warning: a link to no page, an anchor no heading has, a page left out
    of the navigation."""
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                           cwd=ROOT, capture_output=True, text=True, check=False)
    output = build.stdout + build.stderr
    assert build.returncode == 0 and "WARNING" not in output, output
    assert (tmp_path / "site" / "configuration" / "index.html").is_file()  # config/README.md, taken in by docs/hooks.py


# Where users read: every text file of the project but this one (which names what it looks for).
SCANNED = ["README.md", "CHANGELOG.md", "CITATION.cff", "mkdocs.yml", "pyproject.toml", "Snakefile", "measurements/README.md",
           *[f"{folder}/**/*{suffix}" for folder in ("config", "docs", "src", "effects", "workflow", "bench", "tests", ".test")
             for suffix in (".md", ".py", ".yaml", ".yml", ".smk", ".rst", ".txt")]]


def test_nothing_sends_users_to_the_spec_outside_the_repository():
    """A clone has no shared/spec/: the measurement format and the rig are docs/measurements.md and docs/rig.md."""
    files = sorted({path for pattern in SCANNED for path in ROOT.glob(pattern) if path.is_file()} - {Path(__file__).resolve()})
    assert len(files) > 50
    pointing = [f"{path.relative_to(ROOT)}:{number}" for path in files
                for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if "shared/spec" in line]
    assert not pointing, f"these lines point to shared/spec, which a clone does not have: {pointing}"


def number(x: float) -> str:
    """A value as the tables write it: 0.05, 1480, 3.0e+6, 4.8e-3."""
    if x == 0 or 1e-2 <= abs(x) < 1e4:
        return f"{x:g}"
    mantissa, exponent = f"{x:.3e}".split("e")
    mantissa = mantissa.rstrip("0")
    return f"{mantissa}{'0' if mantissa.endswith('.') else ''}e{int(exponent):+d}"


def allowed(lower: float, upper: float, lower_inclusive: bool, upper_inclusive: bool, integer: bool = False) -> str:
    if math.isinf(lower) and math.isinf(upper):
        return "any finite number"
    low = f"{'≥' if lower_inclusive else '>'} {number(lower)}"
    text = low if math.isinf(upper) else f"{number(lower)} {'≤' if lower_inclusive else '<'} x {'≤' if upper_inclusive else '<'} {number(upper)}"
    return f"whole number {low}" if integer else text


def rig_table() -> str:
    """The rig's and the operating condition's parameters of newdyn.model, as docs/rig.md shows them."""
    rows = ["| name | default | unit | what it is | allowed |", "|---|---|---|---|---|"]
    for p in model.PARAMETERS:
        unit = "–" if p.unit == "-" else p.unit
        rows.append(f"| `{p.name}` | {number(p.default)} | {unit} | {p.description} | "
                    f"{allowed(p.lower, p.upper, p.lower_inclusive, p.upper_inclusive, p.integer)} |")
    return "\n".join(rows)


def effects_table() -> str:
    """The built-in effects' parameters, as docs/rig.md shows them."""
    rows = ["| effect | parameter | unit | what it is | default | allowed | fitted over | blind tests draw from |",
            "|---|---|---|---|---|---|---|---|"]
    for kind, effect in effects.builtin().items():
        for p in effect.parameters:
            if p.default is None:
                default = "none: a scenario sets it"
            elif callable(p.default):
                default = f"{number(p.default_value(model.DEFAULTS))} at the default rig (it depends on the rig)"
            else:
                default = number(p.default)
            unit = "–" if p.unit == "-" else p.unit
            rows.append(f"| `{kind}` | `{p.name}` | {unit} | {p.description} | {default} | "
                        f"{allowed(p.lower, p.upper, p.lower_inclusive, p.upper_inclusive)} | "
                        f"{number(p.prior[0])} to {number(p.prior[1])} | {number(p.draw_range[0])} to {number(p.draw_range[1])} |")
    return "\n".join(rows)


@pytest.mark.parametrize("table", [rig_table, effects_table])
def test_rig_tables_are_the_codes(table):
    expected = table()
    assert expected in (DOCS / "rig.md").read_text(encoding="utf-8"), f"docs/rig.md must hold this table:\n\n{expected}\n"


def test_noise_floor_rule_in_the_docs_is_the_codes():
    """docs/measurements.md: without a stated noise level, a record of 256 samples or more needs fs of at least
    256/120 times diagnosis.noise_band_hz, 2133.3 Hz at the default 1000 Hz."""
    band = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["diagnosis"]["noise_band_hz"]
    assert band == 1000.0
    lowest = 256 / 120 * band
    noise.floor_band(5000, lowest * (1 + 1e-9), band)
    with pytest.raises(ValueError, match="fewer than 8"):
        noise.floor_band(5000, lowest * (1 - 1e-6), band)
    assert "2133.3 Hz" in (DOCS / "measurements.md").read_text(encoding="utf-8")


def test_measurement_examples_make_files_a_diagnosis_takes(tmp_path, monkeypatch):
    """Every Python example of docs/measurements.md, run in order in an empty folder, writes files that pass the
    checks a diagnosis makes before it runs (those of the default config)."""
    from newdyn import io

    text = (DOCS / "measurements.md").read_text(encoding="utf-8")
    examples = re.findall(r"^```python\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    assert len(examples) >= 2
    monkeypatch.chdir(tmp_path)
    (tmp_path / "measurements").mkdir()
    namespace = {}
    for example in examples:
        exec(compile(example, "docs/measurements.md", "exec"), namespace)  # noqa: S102 - the docs' own examples
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    written = sorted((tmp_path / "measurements").iterdir())
    assert {path.suffix for path in written} == {".nc", ".csv"}
    for path in written:
        measurement = io.read_measurement(path, config["operating"])
        measurement_checks.check_measurement(measurement, config["diagnosis"]["channels"], config["diagnosis"]["noise_band_hz"], path)
        assert np.all(np.isfinite(measurement.y))


README = ROOT / "README.md"


def test_readme_is_a_guide_with_the_two_commands_and_no_history():
    """README.md: the two commands for a fresh machine verbatim (.ci/run runs the second), the target that diagnoses
    the user's files, its picture; no commit hash and no date (history and measured figures live in docs/ and the
    changelog), and short enough to read in five minutes."""
    text = README.read_text(encoding="utf-8")
    assert "python3 -m venv .venv && . .venv/bin/activate && pip install -e . && snakemake --cores 2\n" in text
    assert "python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[test]' && pytest\n" in text
    assert "snakemake --cores 2 measurements" in text
    assert (ROOT / "docs" / "img" / "error_fall.png").is_file() and "](docs/img/error_fall.png)" in text
    assert not re.findall(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", text), "a commit hash in the README"
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", text), "a date in the README: history belongs in CHANGELOG.md"
    assert len(text.splitlines()) <= 170


def test_readme_links_reach_files_of_the_repository():
    """The site's build checks the pages' links; the README is no page of it, so its relative links are checked here."""
    text = README.read_text(encoding="utf-8")
    targets = [link.split("#")[0] for link in re.findall(r"\]\(([^)\s]+)\)", text) if "://" not in link]
    assert len(targets) > 10
    missing = sorted({target for target in targets if target and not (ROOT / target).exists()})
    assert not missing, f"README.md links to files the repository does not have: {missing}"


def _program(source: str) -> str:
    """The program ``source`` holds, its docstrings (module, classes, functions) and comments aside."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef)) and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)):
            node.body = body[1:]
    return ast.dump(tree)


def test_the_worked_example_of_an_effect_is_the_file_it_names():
    """effects/README.md prints effects/coupling_backlash.py, imports included, so that it loads as printed."""
    readme = (ROOT / "effects" / "README.md").read_text(encoding="utf-8")
    printed = re.search(r"## Worked example.*?```python\n(.*?)```", readme, re.DOTALL).group(1)
    assert _program(printed) == _program((ROOT / "effects" / "coupling_backlash.py").read_text(encoding="utf-8"))


def test_the_architecture_page_names_every_module_in_words():
    """docs/architecture.md's summary under the generated table names each module of the package (a subpackage by its
    folder), so that a module added is placed in words too."""
    text = (DOCS / "architecture.md").read_text(encoding="utf-8")
    summary = text[text.index("In words, by what they do"):text.index("## Where to add things")]
    named = {name.rstrip("/") for name in re.findall(r"`([a-z_]+/?)`", summary)}
    modules = {path.relative_to(ROOT / "src" / "newdyn").parts[0].removesuffix(".py")
               for path in (ROOT / "src" / "newdyn").glob("*") if path.suffix == ".py" or (path / "__init__.py").is_file()}
    assert modules - {"__init__"} == named
