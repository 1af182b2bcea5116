"""What drawing a study's figures costs at two revisions, side by side in one run, and whether they draw the same files.

The figures are those of a study already run (its working folder, e.g. one that `bench_study.py --keep` left): for
each figure job (the study's stages, a diagnosis's figures) Snakemake's dry run gives the command that drew it, which
runs again here, once per revision in turns (`--repeat` times each), with that revision's newdyn first on PYTHONPATH
and every figure written into a scratch folder. Printed are each job's best wall time per revision and their ratio,
then how many PNG and PDF files each pair drew identical to the byte.

Run: python bench/bench_figures.py --study FOLDER [--before REV] [--after REV] [--repeat 3]
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_study import clone, commit  # this script's folder leads sys.path

from newdyn.cli import DIAGNOSIS_FIGURES

# The options of `newdyn plot-diagnosis` that name a figure it writes, as the command line spells them.
DIAGNOSIS_OUTPUTS = tuple(f"--{name.replace('_', '-')}" for name in DIAGNOSIS_FIGURES)


def snakemake(study: Path, *args: str) -> str:
    """The output of Snakemake run with ``args`` in the study's folder."""
    run = subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=study, capture_output=True, text=True,
                         check=False, env={**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"})
    if run.returncode != 0:
        sys.exit(f"snakemake {' '.join(args)} failed in {study}:\n{run.stderr[-3000:]}")
    return run.stdout


def figure_commands(study: Path) -> dict[str, list[str]]:
    """job -> the `newdyn` command (as arguments) that draws its figures, from a dry run of the study's figure rules
    (the workflow's rules named plot_*)."""
    rules = [name for name in snakemake(study, "--list-rules").split() if name.startswith("plot_")]
    output = snakemake(study, "--dry-run", "--printshellcmds", "--cores", "1", "--forcerun", *rules)
    commands = {}
    for line in output.splitlines():
        words = shlex.split(line.split(" > ")[0]) if re.search(r"\bnewdyn plot(-diagnosis)? ", line) else []
        if words:
            words = words[words.index("newdyn"):]
            name = words[2] if words[1] == "plot" else f"diagnosis {words[words.index('--verdict') + 1].split('/')[-2]}"
            commands[name] = words
    return commands


def into(words: list[str], folder: Path) -> list[str]:
    """``words`` with every figure it writes moved into ``folder`` (each name made unique by its position)."""
    words = list(words)
    if words[1] == "plot":
        at = words.index("--figures") + 1
        figures = json.loads(words[at])
        for i, figure in enumerate(figures):
            for key in ("png", "chi2_png"):
                if key in figure:
                    figure[key] = str(folder / f"{i:03d}_{key}_{Path(figure[key]).name}")
        words[at] = json.dumps(figures)
    else:
        for option in DIAGNOSIS_OUTPUTS:
            at = words.index(option) + 1
            words[at] = str(folder / Path(words[at]).name)
    return words


def draw(words: list[str], study: Path, source: Path, folder: Path) -> float:
    """Wall time [s] of drawing one job's figures with the newdyn of ``source`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "newdyn.cli", *into(words, folder)[1:]]
    start = time.perf_counter()
    run = subprocess.run(command, cwd=study, env={**os.environ, "PYTHONPATH": str(source)}, capture_output=True,
                         text=True, check=False)
    elapsed = time.perf_counter() - start
    if run.returncode != 0:
        sys.exit(f"{' '.join(words[:3])} failed with {source}:\n{run.stderr[-3000:]}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--study", type=Path, required=True, help="a study's working folder, its results drawn")
    parser.add_argument("--before", default="main", help="the revision to compare with (default: main)")
    parser.add_argument("--after", default="HEAD", help="the revision measured (default: HEAD)")
    parser.add_argument("--repeat", type=int, default=3, help="times each job is drawn per revision (best kept)")
    args = parser.parse_args()

    study = args.study.resolve()
    commands = figure_commands(study)
    revisions = {"before": commit(args.before), "after": commit(args.after)}
    with tempfile.TemporaryDirectory() as scratch:
        sources = {}
        for label, revision in revisions.items():
            clone(revision, Path(scratch, label))
            sources[label] = Path(scratch, label, "src")
        best = {(job, label): float("inf") for job in commands for label in revisions}
        for _ in range(args.repeat):  # in turns, so that the machine's drift falls on both alike
            for job, words in commands.items():
                for label in revisions:
                    folder = Path(scratch, "figures", label, re.sub(r"\W", "_", job))
                    best[job, label] = min(best[job, label], draw(words, study, sources[label], folder))

        print(f"{args.study}, best of {args.repeat}, {time.strftime('%Y-%m-%d %H:%M')}")
        print(f"{'job':34s} {'before ' + revisions['before']:>16s} {'after ' + revisions['after']:>16s} {'ratio':>7s}")
        for job in commands:
            old, new = best[job, "before"], best[job, "after"]
            print(f"{job:34s} {old:15.1f}s {new:15.1f}s {new / old:6.2f}x")
        old, new = (sum(best[job, label] for job in commands) for label in revisions)
        print(f"{'all':34s} {old:15.1f}s {new:15.1f}s {new / old:6.2f}x")
        before = Path(scratch, "figures", "before")
        files = sorted(path.relative_to(before) for path in before.rglob("*") if path.suffix in (".png", ".pdf"))
        same = [path for path in files if filecmp.cmp(before / path, Path(scratch, "figures", "after", path), shallow=False)]
        print(f"files identical to the byte: {len(same)} of {len(files)}")
        for path in sorted(set(files) - set(same)):
            print(f"  differs: {path}")


if __name__ == "__main__":
    main()
