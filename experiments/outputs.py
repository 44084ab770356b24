"""Where an experiment script writes.

Committed results (``results/...``) are rewritten only by a run that reproduces them: all
settings at their defaults, or an explicit ``--out``. A run with other settings writes to
``results/tmp/...`` (ignored by git) and says so, so that a ``--seed 3`` run never mixes
with a committed 100-seed table.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from pathlib import Path

__all__ = ["output_path", "scratch_path", "write_report"]


def scratch_path(committed: Path) -> Path:
    """``results/paper`` -> ``results/tmp/paper`` (``.../results/x`` -> ``.../results/tmp/x``)."""
    committed = Path(committed)
    return committed.parent / "tmp" / committed.name


def output_path(args: argparse.Namespace, parser: argparse.ArgumentParser, committed: Path, *,
                out_attr: str = "out", ignore: Iterable[str] = ("progress",)) -> Path:
    """The output path of a script run.

    Args:
        args: the parsed arguments; ``args.<out_attr>`` is None unless ``--out`` was given.
        parser: the parser (its defaults say which settings reproduce the committed result).
        committed: the committed result's path.
        ignore: settings that do not change the result (e.g. progress bars).

    Returns:
        ``--out`` if given; ``committed`` if every other setting is at its default;
        otherwise :func:`scratch_path` of ``committed`` (announced on stderr).
    """
    given = getattr(args, out_attr)
    if given is not None:
        return Path(given)
    skip = {out_attr, *ignore}
    changed = sorted(k for k, v in vars(args).items() if k not in skip and v != parser.get_default(k))
    if not changed:
        return Path(committed)
    tmp = scratch_path(committed)
    flags = ", ".join("--" + k.replace("_", "-") for k in changed)
    print(f"non-default settings ({flags}): writing to {tmp} (ignored by git), not to the committed {committed}; "
          "give --out to choose the place", file=sys.stderr)
    return tmp


def write_report(path: Path, text: str) -> str:
    """Write a Markdown report (creating its folder), print it and say where; returns ``text``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(text)
    print(f"written to {path}")
    return text
