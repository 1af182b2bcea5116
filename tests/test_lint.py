"""The code is lint-clean: ruff on the Python, snakemake --lint and snakefmt on the workflow."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOOLS = Path(sys.executable).parent


def test_python_is_ruff_clean():
    ruff = subprocess.run([TOOLS / "ruff", "check", "--no-cache", "src", "tests", "bench", "effects", "docs"], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    assert ruff.returncode == 0, ruff.stdout + ruff.stderr


def test_workflow_is_lint_clean_and_snakefmt_formatted():
    lint = subprocess.run([sys.executable, "-m", "snakemake", "--lint"], cwd=ROOT, capture_output=True, text=True, check=False)
    assert lint.returncode == 0 and "Lints for" not in lint.stdout + lint.stderr, lint.stdout + lint.stderr
    files = [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]
    fmt = subprocess.run([TOOLS / "snakefmt", "--check", *map(str, files)], capture_output=True, text=True, check=False)
    assert fmt.returncode == 0, fmt.stderr


def test_every_rule_keeps_a_log_and_a_benchmark_and_asks_for_memory_and_time():
    """Each job's output and its measured time and memory land under results/, and each rule asks a cluster for the
    memory and time sized from them; rules made in a loop (one per variant) as well."""
    rules = re.compile(r"^(?P<indent> *)rule(?: (?P<name>\w+))?:\n(?P<body>(?:(?P=indent)[ \t]+.*\n|\n)+)", re.MULTILINE)
    for path in sorted((ROOT / "workflow" / "rules").glob("*.smk")):
        text = path.read_text()
        assert len(list(rules.finditer(text))) == len(re.findall(r"^ *rule\b", text, re.MULTILINE)), path.name
        for rule in rules.finditer(text):
            indent = rule["indent"] + "    "
            name = rule["name"] or re.search(rf"^{indent}name:\n\s+(.+)$", rule["body"], re.MULTILINE).group(1)
            for directive in ("log:", "benchmark:", "resources:", "    mem_mb=", "    runtime="):
                assert re.search(rf"^{indent}{directive}", rule["body"], re.MULTILINE), f"{path.name}: rule {name} has no {directive}"
