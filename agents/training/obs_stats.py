"""Observation-normalisation statistics in a file format that runs no code when read.

SB3 saves a ``VecNormalize`` wrapper with :mod:`pickle`: loading such a file can execute
arbitrary code. Evaluation needs only four things from it (the running mean and variance of
the observations, the clip bound and epsilon), so training writes those, next to SB3's
pickle, as JSON (``vecnormalize.json``; checkpoints ``model_vecnormalize_<steps>_steps.json``)
and :func:`agents.training.load_agent` reads only that. SB3's pickle is kept for resuming
training (``--resume``), which must restore the complete wrapper.

Convert a pickle you trust (for instance a run trained before this format existed)::

    python -m agents.training.obs_stats runs/<run>/vecnormalize.pkl   # writes runs/<run>/vecnormalize.json

That command unpickles the file: run it only on files you would run as code.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from auv_follow_env._files import check_size

__all__ = ["ObsStats", "FORMAT", "write_obs_stats", "read_obs_stats", "stats_from_vecnormalize",
           "json_path_for", "convert_pickle", "check_against_config", "main"]

#: identifies the file format (written into every file, checked on reading)
FORMAT = "auv-follow/obs-normalization/v1"


@dataclass(frozen=True)
class ObsStats:
    """What evaluation needs of a VecNormalize wrapper: ``clip((obs - mean) / sqrt(var + epsilon),
    -clip_obs, clip_obs)`` when ``norm_obs`` (SB3's ``VecNormalize.normalize_obs``)."""

    norm_obs: bool  #: observations are normalised (False: pass them through)
    mean: np.ndarray  #: running mean of the observations (float64, shape of one observation)
    var: np.ndarray  #: running variance of the observations (same shape, >= 0)
    count: float  #: samples behind the running statistics
    clip_obs: float  #: bound of the normalised observation (> 0)
    epsilon: float  #: added to the variance (> 0)
    window: int = 0  #: samples the statistics remember (older ones fade out); 0: every sample, as SB3

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """The normalised observation(s), float32 (unchanged if not ``norm_obs``)."""
        if not self.norm_obs:
            return obs
        return np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip_obs,
                       self.clip_obs).astype(np.float32)


def stats_from_vecnormalize(venv: Any) -> ObsStats:
    """The statistics of an SB3 ``VecNormalize`` (flat Box observations only)."""
    rms = venv.obs_rms
    if isinstance(rms, dict):
        raise ValueError("VecNormalize with dict observations is not supported: AUVFollow observations are flat")
    return ObsStats(norm_obs=bool(venv.norm_obs), mean=np.asarray(rms.mean, dtype=np.float64),
                    var=np.asarray(rms.var, dtype=np.float64), count=float(rms.count),
                    clip_obs=float(venv.clip_obs), epsilon=float(venv.epsilon))


def write_obs_stats(stats: ObsStats | Any, path: str | Path) -> Path:
    """Write ``stats`` (an :class:`ObsStats` or an SB3 ``VecNormalize``) as JSON; returns the path.

    Floats are written with :func:`repr` precision, so reading gives the same float64 values.
    """
    if not isinstance(stats, ObsStats):
        stats = stats_from_vecnormalize(stats)
    path = Path(path)
    data = {"format": FORMAT, "norm_obs": stats.norm_obs, "clip_obs": stats.clip_obs, "epsilon": stats.epsilon,
            "count": stats.count, "window": int(stats.window), "mean": stats.mean.tolist(), "var": stats.var.tolist()}
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=1) + "\n")
        tmp.replace(path)  # never leave a half-written file behind
    except BaseException:
        tmp.unlink(missing_ok=True)  # nor its temporary file (disk full, read-only)
        raise
    return path


def _number(data: dict, key: str, path: Path, positive: bool = True) -> float:
    v = data.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"{path}: {key}={v!r} is invalid: must be a finite number{' > 0' if positive else ''}")
    return float(v)


def read_obs_stats(path: str | Path) -> ObsStats:
    """Read a file written by :func:`write_obs_stats` (plain JSON: nothing is executed).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not valid JSON of this format (the message names the file and field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"observation-normalisation statistics {path} do not exist")
    try:
        data = json.loads(check_size(path, "text").read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} is not a normalisation-statistics JSON file: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{path} is not a normalisation-statistics file: format={got!r}, expected {FORMAT!r}")
    if not isinstance(data.get("norm_obs"), bool):
        raise ValueError(f"{path}: norm_obs={data.get('norm_obs')!r} is invalid: must be true or false")
    arrays = {}
    for key in ("mean", "var"):
        try:
            a = np.asarray(data.get(key), dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: {key} is invalid: must be a list of numbers") from None
        if a.ndim != 1 or a.size == 0 or not np.isfinite(a).all():
            raise ValueError(f"{path}: {key} is invalid: must be a non-empty list of finite numbers")
        arrays[key] = a
    if arrays["mean"].shape != arrays["var"].shape:
        raise ValueError(f"{path}: mean has {arrays['mean'].size} entries but var has {arrays['var'].size}")
    if (arrays["var"] < 0).any():
        raise ValueError(f"{path}: var is invalid: must be >= 0")
    return ObsStats(norm_obs=data["norm_obs"], mean=arrays["mean"], var=arrays["var"],
                    count=_number(data, "count", path, positive=False),
                    clip_obs=_number(data, "clip_obs", path), epsilon=_number(data, "epsilon", path),
                    window=_window(data, path))


def _window(data: dict, path: Path) -> int:
    """The statistics' window (absent in files written before it was recorded: 0, never forget)."""
    w = data.get("window", 0)
    if isinstance(w, bool) or not isinstance(w, int) or w < 0:
        raise ValueError(f"{path}: window={w!r} is invalid: must be a whole number of samples >= 0")
    return w


#: SB3 VecNormalize defaults (what a run's ``normalize`` section means when it omits a key)
_VECNORM_DEFAULTS = {"norm_obs": True, "clip_obs": 10.0, "epsilon": 1e-8}


def check_against_config(stats: ObsStats, normalize: Any, stats_path: str | Path, config_path: str | Path) -> None:
    """Refuse statistics that contradict the run's ``config.yaml`` ``normalize`` section
    (``norm_obs``, ``clip_obs``, ``epsilon``; SB3's defaults where the section omits them).

    Raises:
        ValueError: naming both files, the field and the two values.
    """
    if not isinstance(normalize, dict):
        return
    for key, default in _VECNORM_DEFAULTS.items():
        want = normalize.get(key, default)
        got = getattr(stats, key)
        same = (bool(want) == bool(got)) if key == "norm_obs" else (
            isinstance(want, (int, float)) and math.isclose(float(want), float(got), rel_tol=1e-12, abs_tol=0.0))
        if not same:
            raise ValueError(f"{stats_path}: {key}={got!r} contradicts {config_path} (normalize.{key}={want!r}): "
                             "the statistics are not this run's")


def json_path_for(pickle_path: str | Path) -> Path:
    """``.../vecnormalize.pkl`` -> ``.../vecnormalize.json`` (same for checkpoint names)."""
    return Path(pickle_path).with_suffix(".json")


def convert_pickle(pickle_path: str | Path, json_path: str | Path | None = None) -> Path:
    """Write the JSON statistics of an SB3 ``VecNormalize`` pickle (next to it by default).

    This *unpickles* ``pickle_path``: use it only on files you trust like code.
    """
    import pickle

    pickle_path = Path(pickle_path)
    with open(pickle_path, "rb") as f:
        venv = pickle.load(f)  # noqa: S301 (trusted file, see the docstring)
    if not hasattr(venv, "obs_rms") or not hasattr(venv, "clip_obs"):
        raise ValueError(f"{pickle_path} does not hold a VecNormalize (got {type(venv).__name__})")
    return write_obs_stats(venv, json_path if json_path is not None else json_path_for(pickle_path))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agents.training.obs_stats", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pickles", nargs="+", type=Path, help="VecNormalize .pkl files you trust (they are unpickled)")
    args = p.parse_args(argv)
    for pkl in args.pickles:
        if not pkl.is_file():
            p.error(f"argument pickles: {pkl} does not exist")
    for pkl in args.pickles:
        print(f"wrote {convert_pickle(pkl)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())


#: a checkpoint's file stem: ``<prefix>_<steps>_steps``
_CKPT = re.compile(r"^(?P<prefix>.+)_(?P<steps>\d+)_steps$")


def _stats_path(model_path: Path, suffix: str) -> Path:
    """The normalisation statistics saved with a model (``vecnormalize<suffix>``) or a checkpoint
    (``<prefix>_vecnormalize_<steps>_steps<suffix>``); other names: ``vecnormalize<suffix>`` beside."""
    m = _CKPT.match(model_path.stem)
    if model_path.name != "model.zip" and m:
        return model_path.with_name(f"{m['prefix']}_vecnormalize_{m['steps']}_steps{suffix}")
    return model_path.with_name(f"vecnormalize{suffix}")
