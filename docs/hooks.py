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
