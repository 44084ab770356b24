"""Size limits on the files a user gives us (run directories, benchmark folders, sweep state, link
traces): a file above its limit is refused by name before it is read, so a huge or sparse file
costs a stat, not the machine's memory."""

from __future__ import annotations

from pathlib import Path

__all__ = ["LIMITS", "check_size"]

MB = 1 << 20
#: kind of file -> the largest accepted size [bytes]; each is far above what this project writes
#: (the committed benchmark's leaderboard.csv is 0.08 MB, its episodes.parquet 1.7 MB, a model.zip < 3 MB)
LIMITS = {
    "text": 16 * MB,       # config.yaml, sweep.yaml, trial_state.json, vecnormalize.json, benchmark.json
    "table": 256 * MB,     # leaderboard.csv, eval.csv, a link trace (CSV)
    "parquet": 2048 * MB,  # episodes.parquet, traces.parquet, a link trace (Parquet)
    "model": 2048 * MB,    # model.zip
}


def check_size(path: str | Path, kind: str) -> Path:
    """``path`` as a Path, or a ValueError naming it when it is larger than :data:`LIMITS` [kind].

    A missing file passes (the reader reports it in its own words)."""
    p = Path(path)
    limit = LIMITS[kind]
    try:
        size = p.stat().st_size
    except OSError:
        return p
    if size > limit:
        raise ValueError(f"{p} is {size / MB:,.0f} MB: larger than the {limit / MB:,.0f} MB this project reads "
                         f"from a {kind} file of its kind (auv_follow_env._files.LIMITS); is it the right file?")
    return p
