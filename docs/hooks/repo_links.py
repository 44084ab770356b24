"""mkdocs hook: links from the docs to repository files outside docs/ work on the site too.

The pages link to files as they lie in the repository (``../results/floors/floors.md`` from
``docs/benchmark.md``, ``../CHANGELOG.md``), so the links work where the Markdown is read on its
own. On the site those files are outside ``docs_dir``; this hook

* ``on_files``: adds every repository file that a page links to (and, for Markdown files, what
  they link to in turn) to the site at its repository path, e.g. ``results/floors/floors.md``;
* ``on_page_markdown``: rewrites each such link to that site path, relative to the page.

Only files inside the repository are added (never ``.venv``, ``.git`` or anything a link leaves
the repository for); a link to a file that does not exist is left alone, so ``mkdocs build
--strict`` still fails on it.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

LINK = re.compile(r"(!?\[[^\]\n]*\]\()([^)\s#]+)(#[^)\s]*)?(\))")
FENCE = re.compile(r"^(```|~~~).*?^\1\s*$", re.M | re.S)
SKIP_PARTS = {".venv", ".git", "site", "__pycache__", "node_modules"}


def _root(config) -> Path:
    return Path(config["docs_dir"]).resolve().parent


def _repo_location(src_uri: str, root: Path) -> str:
    """Where a page lies in the repository: a copied file at its own path, a docs page (real or
    generated) under docs/."""
    if not src_uri.startswith("docs/") and (root / src_uri).is_file() and _copied.get(src_uri):
        return src_uri
    return "docs/" + src_uri


def _resolve(page_repo: str, target: str) -> str | None:
    """The repository path a relative link from ``page_repo`` points to, or None (URLs, absolute
    paths and links that leave the repository)."""
    if re.match(r"[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("/"):
        return None
    path = posixpath.normpath(posixpath.join(posixpath.dirname(page_repo), target))
    if path.startswith("../") or path == "..":
        return None
    return path


def _site_path(repo_path: str) -> str:
    return repo_path[len("docs/"):] if repo_path.startswith("docs/") else repo_path


def _links(markdown: str):
    text = FENCE.sub("", markdown)
    for m in LINK.finditer(text):
        yield m.group(2)


_copied: dict[str, bool] = {}


def on_files(files, config):
    root = _root(config)
    docs_dir = Path(config["docs_dir"]).resolve()
    _copied.clear()
    todo = []
    for f in files:
        if f.src_uri.endswith(".md"):
            text = Path(f.abs_src_path).read_text(encoding="utf-8") if f.abs_src_path else (f.content_string or "")
            todo.append(("docs/" + f.src_uri, text))
    while todo:
        page_repo, text = todo.pop()
        for target in _links(text):
            repo_path = _resolve(page_repo, target)
            if repo_path is None or repo_path.startswith("docs/") or repo_path in _copied:
                continue
            path = (root / repo_path).resolve()
            if not path.is_file() or root not in path.parents or docs_dir in path.parents \
                    or SKIP_PARTS & set(Path(repo_path).parts):
                continue
            _copied[repo_path] = True
            files.append(File(repo_path, str(root), config["site_dir"], config["use_directory_urls"]))
            if repo_path.endswith(".md"):
                todo.append((repo_path, path.read_text(encoding="utf-8")))
    return files


def on_page_markdown(markdown, page, config, files):
    root = _root(config)
    page_repo = _repo_location(page.file.src_uri, root)
    page_dir = posixpath.dirname(page.file.src_uri)

    def fix(m: re.Match) -> str:
        repo_path = _resolve(page_repo, m.group(2))
        if repo_path is None:
            return m.group(0)
        site = _site_path(repo_path)
        if files.get_file_from_path(site) is None:
            return m.group(0)  # left for mkdocs to report
        new = posixpath.relpath(site, page_dir or ".")
        return f"{m.group(1)}{new}{m.group(3) or ''}{m.group(4)}"

    out, pos = [], 0
    for fence in FENCE.finditer(markdown):
        out.append(LINK.sub(fix, markdown[pos:fence.start()]))
        out.append(fence.group(0))
        pos = fence.end()
    out.append(LINK.sub(fix, markdown[pos:]))
    return "".join(out)
