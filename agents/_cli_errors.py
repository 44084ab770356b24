"""The CLI's refusals after parsing, shared by :mod:`agents.cli` and :mod:`agents.data_commands`:
a refused setting exits 2 with one line naming the flag."""

from __future__ import annotations

import os
from pathlib import Path


class _Refused(Exception):
    """A setting refused after parsing: (flag, message)."""


def _check_writable(path: Path, flag: str, want_dir: bool) -> None:
    """Refuse an output path that cannot be written, without creating anything."""
    if path.exists():
        if want_dir and not path.is_dir():
            raise _Refused(flag, f"{path} exists and is not a directory")
        if not want_dir and path.is_dir():
            raise _Refused(flag, f"{path} is a directory: give a file name, e.g. {path / 'eval.csv'}")
    anc = path if path.is_dir() else path.parent  # an existing file is overwritten: its directory must be writable
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise _Refused(flag, f"cannot create {path}: {anc} is not a directory")
    if not os.access(anc, os.W_OK):
        raise _Refused(flag, f"cannot write {path}: {anc} is not writable")
