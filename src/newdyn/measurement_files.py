"""How a measurements folder is laid out: which files are measurements, how they may be named, and the table of
operating conditions beside a machine's recordings.  Imports nothing, so that both the catalog (which runs while
Snakemake parses) and the reader (:mod:`newdyn.io`) take it from one place."""

import re

SUFFIXES = (".nc", ".csv")
NAME = re.compile(r"[A-Za-z0-9_.-]+")  # of a file without its suffix, and of a machine's folder
CONDITIONS = "conditions.csv"  # beside recordings: their operating conditions (newdyn.io.recorded_condition)
