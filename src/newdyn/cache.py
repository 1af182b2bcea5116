"""newdyn's cache folder and the small JSON files that remember answers between processes.

The folder (``NEWDYN_CACHE``, default ``~/.cache/newdyn``) holds the compiled kernels and answers keyed by a
hash of everything they were computed from, so that any later process that shares it — the next parse of the
Snakefile, a cluster job on another node — reads them instead of computing them again.  Only the standard
library is imported here: the Snakefile's parse imports this.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

Answer = TypeVar("Answer")
_answers: dict[Path, dict] = {}  # each answers file as this process last read or wrote it


def folder() -> Path:
    return Path(os.environ.get("NEWDYN_CACHE") or Path.home() / ".cache" / "newdyn")


def read_json(path: str | os.PathLike) -> dict:
    """The JSON object in ``path``; empty when there is none or it cannot be read (it is then computed again)."""
    try:
        document = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return document if isinstance(document, dict) else {}


def write_json(path: str | os.PathLike, document: Mapping) -> None:
    """Write atomically, so that processes reading at the same time never see half a file; a folder that cannot be
    written to only means the answer is computed again next time."""
    path, written = Path(path), None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.", delete=False) as f:
            written = Path(f.name)
            json.dump(document, f)
        os.replace(written, path)
    except OSError:
        if written is not None:
            written.unlink(missing_ok=True)


def remembered(path: str | os.PathLike, key: str, compute: Callable[[], Answer],
               keep: Callable[[Answer], bool] = lambda answer: True) -> Answer:
    """The answer under ``key`` in the JSON object ``path`` (read once per process), else ``compute()``'s, added to
    it when ``keep`` says so.  ``key`` and the file's name must name everything a kept answer depends on; answers
    are JSON (a tuple comes back as a list)."""
    path = Path(path)
    answers = _answers.setdefault(path, read_json(path))
    if key in answers:
        return answers[key]
    answer = compute()
    if keep(answer):
        answers[key] = answer
        write_json(path, answers)
    return answer
