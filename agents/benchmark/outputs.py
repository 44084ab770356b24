"""Writing and reading a benchmark's outputs: provenance, CSV / Parquet / Markdown / PNG files
replaced as one set (never half-written), and :func:`load_result`."""

from __future__ import annotations

import contextlib
import json
import platform
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.leaderboard import leaderboard_markdown, plot_leaderboard
from auv_follow_env._files import check_size
from auv_follow_env._signals import STOP_SIGNALS, deferred_signals


def provenance(config: Mapping[str, Any]) -> dict[str, Any]:
    """The configuration and the versions / git commit a result was made with."""
    import scipy

    from agents.training.rundir import versions

    v = versions()
    v.update({"pandas": pd.__version__, "scipy": scipy.__version__, "python_impl": platform.python_implementation()})
    return {"config": json.loads(json.dumps(config, default=str)), "versions": v}


@dataclass
class BenchmarkResult:
    """What :func:`benchmark` returns (and writes)."""

    episodes: pd.DataFrame
    leaderboard: pd.DataFrame
    provenance: dict[str, Any]
    files: dict[str, Path] = field(default_factory=dict)
    traces: pd.DataFrame | None = None  #: per-step replay episodes (see :func:`replay_traces`)


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    """A plain CSV (``pd.read_csv(path)`` reads it as written); its provenance is benchmark.json
    beside it, which records the file's SHA-256 (:data:`PLAIN_FILES`)."""
    df.to_csv(path, index=False)


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


#: files without room for a provenance stamp: benchmark.json's "files" section holds their SHA-256
PLAIN_FILES: tuple[str, ...] = ("leaderboard.csv",)


def _write_parquet(df: pd.DataFrame, path: Path, prov: Mapping[str, Any]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"auv_follow_provenance"] = json.dumps(prov, default=str).encode()
    pq.write_table(table.replace_schema_metadata(meta), path)


#: the files :func:`benchmark` writes (key -> file name); each records the run's provenance
OUTPUT_FILES: dict[str, str] = {"episodes": "episodes.parquet", "leaderboard_csv": "leaderboard.csv",
                                "leaderboard_md": "leaderboard.md", "leaderboard_png": "leaderboard.png",
                                "traces": "traces.parquet", "provenance": "benchmark.json"}


class OutputWriteError(OSError):
    """A set of output files could not be written (full disk, no permission); the previous
    files in the folder are kept (the message names the folder and the reason)."""


def replace_set(stage: Path, out: Path, names: Sequence[str]) -> dict[str, Path]:
    """Move the files ``names`` from ``stage`` into ``out`` as one set: the files of the same
    names already in ``out`` are moved aside first and put back if any move fails or is
    interrupted, so ``out`` holds either the previous set or the complete new one, never a mix.
    Ctrl-C is held back while the files move. ``stage`` must be on the file system of ``out``.

    Returns:
        ``{name: out / name}``.

    Raises:
        OutputWriteError: a move failed (the previous set is back in place; if even that
            failed, the message says where the previous files are).
    """
    import os
    import shutil
    import tempfile

    aside = Path(tempfile.mkdtemp(prefix=".benchmark-previous-", dir=out))
    moved: list[str] = []
    placed: list[str] = []
    with deferred_signals(STOP_SIGNALS):  # (delivered when the files are in place)
        try:
            for name in names:
                if os.path.lexists(out / name):
                    os.replace(out / name, aside / name)
                    moved.append(name)
            for name in names:
                os.replace(stage / name, out / name)
                placed.append(name)
        except BaseException as exc:
            lost = []
            for name in placed:
                try:
                    os.replace(out / name, stage / name)
                except OSError:
                    lost.append(name)
            for name in moved:
                try:
                    os.replace(aside / name, out / name)
                except OSError:
                    lost.append(name)
            if lost:
                raise OutputWriteError(f"{out}: writing the new files failed ({_first_line(exc)}) and putting the "
                                       f"previous ones back failed too: they are in {aside}") from exc
            shutil.rmtree(aside, ignore_errors=True)
            if isinstance(exc, OSError):
                raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)}): its previous "
                                       "files are kept") from exc
            raise
        shutil.rmtree(aside, ignore_errors=True)  # (before a held-back Ctrl-C is delivered)
    return {name: out / name for name in names}


def write_outputs(out: Path, episodes: pd.DataFrame, board: pd.DataFrame, prov: Mapping[str, Any],
                  traces: pd.DataFrame) -> dict[str, Path]:
    """Write the benchmark files into ``out``: all of them into a temporary folder inside
    ``out`` first, then moved into place as one set (:func:`replace_set`: an interruption or a
    failure at any point leaves the previous files, all of them; :func:`load_result` refuses a
    folder whose files disagree).

    Raises:
        OutputWriteError: a file could not be written (full disk, no permission): nothing in
            ``out`` was changed.
    """
    import shutil
    import tempfile

    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=".benchmark-partial-", dir=out))
    except OSError as exc:
        raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)})") from exc
    ok = False
    try:
        staged = {k: stage / name for k, name in OUTPUT_FILES.items()}
        try:
            _write_parquet(episodes, staged["episodes"], prov)
            _write_csv(board, staged["leaderboard_csv"])
            staged["leaderboard_md"].write_text(leaderboard_markdown(board, prov) + "\n")
            plot_leaderboard(board, staged["leaderboard_png"], prov=prov)
            _write_parquet(traces, staged["traces"], prov)
            files = {name: {"sha256": _sha256(stage / name)} for name in PLAIN_FILES}
            staged["provenance"].write_text(json.dumps({**prov, "files": files}, indent=1, default=str) + "\n")
        except OSError as exc:
            raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)}): its previous "
                                   "files are kept") from exc
        placed = replace_set(stage, out, list(OUTPUT_FILES.values()))
        ok = True
        return {k: placed[name] for k, name in OUTPUT_FILES.items()}
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if created and not ok:
            with contextlib.suppress(OSError):
                out.rmdir()  # the folder this call made, if it is still empty


def _prov_key(prov: Any) -> str:
    return json.dumps(prov, sort_keys=True, default=str)


def load_result(out_dir: str | Path) -> BenchmarkResult:
    """Read a benchmark written by :func:`benchmark` back (episodes, leaderboard, provenance,
    and the replay traces if present).

    Raises:
        FileNotFoundError: a file of the benchmark is missing (names it).
        ValueError: a file is corrupt, or the files come from different runs (names them).
    """
    import pyarrow.parquet as pq

    out = Path(out_dir)
    for name in ("episodes.parquet", "leaderboard.csv", "benchmark.json", "traces.parquet"):
        if name != "traces.parquet" and not (out / name).is_file():
            raise FileNotFoundError(f"{out / name} does not exist: run `auv-follow benchmark --out {out}`")
        check_size(out / name, {".json": "text", ".csv": "table"}.get(Path(name).suffix, "parquet"))
    try:
        prov = json.loads((out / "benchmark.json").read_text())
        if not isinstance(prov, dict) or not isinstance(prov.get("config"), dict):
            raise ValueError("expected a mapping with a 'config' section")
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{out / 'benchmark.json'} is not a benchmark provenance file: {_first_line(exc)}") from None
    stamps: dict[str, Any] = {}

    def parquet(name: str) -> pd.DataFrame:
        try:
            table = pq.read_table(out / name)
        except Exception as exc:  # noqa: BLE001 (pyarrow raises many kinds for a broken file)
            raise ValueError(f"{out / name} is not a readable parquet file: {_first_line(exc)}") from None
        meta = (table.schema.metadata or {}).get(b"auv_follow_provenance")
        stamps[name] = json.loads(meta) if meta else None
        return table.to_pandas()

    files = prov.pop("files", None) if isinstance(prov.get("files"), dict) else None
    episodes = parquet("episodes.parquet")
    try:
        with open(out / "leaderboard.csv") as f:
            first = f.readline()
        stamped = first.startswith("# provenance: ")  # a folder written before the CSV was plain
        stamps["leaderboard.csv"] = json.loads(first[len("# provenance: "):]) if stamped else None
        board = pd.read_csv(out / "leaderboard.csv", skiprows=1 if stamped else 0)
    except (UnicodeDecodeError, ValueError, pd.errors.ParserError) as exc:
        raise ValueError(f"{out / 'leaderboard.csv'} is not a leaderboard CSV: {_first_line(exc)}") from None
    traces = parquet("traces.parquet") if (out / "traces.parquet").is_file() else None
    want = _prov_key(prov)
    mixed = sorted(name for name, st in stamps.items() if st is not None and _prov_key(st) != want)
    for name, rec in (files or {}).items():
        if name in PLAIN_FILES and isinstance(rec, dict) and (out / name).is_file() and \
                rec.get("sha256") != _sha256(out / name):
            raise ValueError(f"{out / name} is not the file this benchmark wrote (its SHA-256 differs from the one "
                             f"in {out / 'benchmark.json'}): edited, or from different benchmark runs; run the "
                             "benchmark again")
    if mixed:
        raise ValueError(f"{', '.join(str(out / m) for m in mixed)} and {out / 'benchmark.json'} are from different "
                         f"benchmark runs (their provenance differs): run the benchmark again")
    need = {"tier", "policy", "kind", "true_steady_mean_iqm", "true_steady_mean_iqm_lo", "true_steady_mean_iqm_hi"}
    if not need <= set(board.columns):
        raise ValueError(f"{out / 'leaderboard.csv'} lacks columns {sorted(need - set(board.columns))}")
    lacks = sorted({"tier", "policy", "seed"} - set(episodes.columns))
    if lacks:
        raise ValueError(f"{out / 'episodes.parquet'} lacks columns {lacks}")
    from agents.benchmark.floors import LEGACY_LABELS

    for frame in (episodes, board, traces):  # a folder from before a floor's rename: read with today's name
        if frame is not None and "policy" in frame:
            frame["policy"] = frame["policy"].replace(LEGACY_LABELS)
    res = BenchmarkResult(episodes, board, prov, {})
    res.traces = traces
    return res


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]
