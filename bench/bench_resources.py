"""What each rule's jobs used against what the rule asks a cluster for: the peak wall time and memory (max RSS) in
a study's benchmark files (results/benchmarks/ and each hidden set's results/<set>/benchmarks/) beside the rule's
declared runtime and mem_mb (workflow/rules/*.smk, first attempt), and the headroom between them.

Run after a study: python bench/bench_resources.py [results folder ...]   (default: results)
"""

from __future__ import annotations

import csv
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def declared() -> dict[str, dict[str, int]]:
    """rule -> {"mem_mb": MB, "runtime": minutes} as its first attempt asks for them; a rule made in a loop (one per
    variant) goes by the folder of its benchmark files, as its jobs' measurements do."""
    found = {}
    rules = re.compile(r"^(?P<indent> *)rule(?: (?P<name>\w+))?:\n(?P<body>(?:(?P=indent)[ \t]+.*\n|\n)+)", re.MULTILINE)
    for path in sorted((ROOT / "workflow" / "rules").glob("*.smk")):
        for rule in rules.finditer(path.read_text()):
            body = rule["body"]
            name = rule["name"] or re.search(r'benchmarks/(\w+)', body).group(1)
            found[name] = {key: int(value) for key, value in re.findall(r"^ +(mem_mb|runtime)=per_attempt\((\d+)\)", body, re.MULTILINE)}
    return found


def measured(folders: list[Path]) -> dict[str, dict[str, float]]:
    """rule -> jobs, peak wall time [s] and peak max RSS [MB] over every benchmark file under ``folders``."""
    found: dict[str, dict[str, float]] = {}
    for folder in folders:
        for path in folder.rglob("benchmarks/**/*.tsv"):
            rule = Path(path.as_posix().split("/benchmarks/", 1)[1]).parts[0].removesuffix(".tsv")
            with path.open() as f:
                for row in csv.DictReader(f, delimiter="\t"):
                    peak = found.setdefault(rule, {"jobs": 0, "s": 0.0, "max_rss": 0.0})
                    peak["jobs"] += 1
                    peak["s"] = max(peak["s"], float(row["s"]))
                    peak["max_rss"] = max(peak["max_rss"], float(row["max_rss"]) if row["max_rss"] != "NA" else 0.0)
    return found


def main() -> None:
    folders = [Path(arg) for arg in sys.argv[1:]] or [Path("results")]
    asked, used = declared(), measured(folders)
    print(f"{'rule':20s} {'jobs':>5s} {'peak time':>10s} {'asked':>7s} {'room':>6s} {'peak memory':>12s} {'asked':>8s} {'room':>6s}")
    for rule in sorted(asked):
        if rule not in used:
            print(f"{rule:20s} {0:5d} {'not run':>10s}")
            continue
        peak, ask = used[rule], asked[rule]
        print(f"{rule:20s} {peak['jobs']:5.0f} {peak['s']:9.1f}s {ask['runtime']:5d}min {ask['runtime'] * 60 / peak['s']:5.1f}x "
              f"{peak['max_rss']:9.0f} MB {ask['mem_mb']:5d} MB {ask['mem_mb'] / max(peak['max_rss'], 1.0):5.1f}x")


if __name__ == "__main__":
    main()
