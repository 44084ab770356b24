"""One self-contained HTML page from a benchmark directory (``auv-follow report``).

The page embeds plotly.js inline (no CDN, no server: open the file) and shows

* the leaderboard: one table per tier with every column explained on the page, and a chart
  of the steady-state IQM with its 95 % CI per tier;
* breakdowns over the drawn conditions: steady-state error vs latency and vs loss rate
  (one panel per tier, binned within the tier, IQM per bin);
* one episode per policy on the replay tier: forces over time with the force limits, and
  along-track / cross-track error over time (error of the follower from the true reference,
  in the true target's heading frame);
* the delayed (received), estimated (the controller's own reference minus the offset p_d)
  and true target on one episode of the replay tier (Hard when it was benchmarked);
* an episode replay (play / slider): follower, true target and what the follower received,
  for a chosen policy and seed.

Colours: one per policy, the same in every chart and beside its name in the table, fixed once
from the leaderboard: families by hue (floors grey, classical controllers warm, learned
policies cool, others magenta), the best of each family the most distinct. The charts draw the
best few of each family on each tier (:data:`SHOWN_PER_FAMILY`) and the floors; the others are
one click on the legend (or the "all policies" button) away.

The page is built from the stored tables alone: the time plots and the replay come from the
benchmark's ``traces.parquet`` (one episode per tier and policy, recorded when the benchmark
ran). Building a report never loads a ``model.zip`` (an SB3 file can run code when loaded):
where a folder has no trace of a policy, a scripted controller of this package is re-run by
name (deterministic: same seed, same episode) and a learned policy is left out of the time
plots, with a note. Every value read from the folder is escaped before it reaches the page,
only the folder's own files are read (a symbolic link out of the folder is refused), and every
value the page uses is checked first: a malformed file is refused with a ValueError naming the
file and the column.
"""

from __future__ import annotations

import html
import json
import math
import os
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd

from agents.benchmark.floors import CONTROL_FLOOR, INFORMATION_FLOOR, REFERENCE_KIND
from agents.benchmark.leaderboard import scores
from agents.benchmark.outputs import load_result
from agents.benchmark.policies import _controllers
from agents.benchmark.protocol import resolve_tier
from agents.benchmark.traces import rollout_episode

__all__ = ["write_report", "binned_breakdown", "SHOWN_PER_FAMILY"]

#: policies of each family drawn by default in the charts, per tier (the others: a legend click away)
SHOWN_PER_FAMILY = 3

# families by hue; within a family the colours are in the order they are handed out (the
# policies drawn by default pick the most distinct of the free ones, see _policy_styles)
_FAMILIES = ("floor", "classical", "learned", "other")
_FAMILY_OF_KIND = {REFERENCE_KIND: "floor", "classical": "classical", "learned": "learned"}
_FAMILY_NAMES = {"floor": "floors (grey)", "classical": "classical controllers (warm colours)",
                 "learned": "learned policies (cool colours)", "other": "other policies (magenta)"}
_PALETTES = {
    "floor": ("#7f7f7f", "#3d3d3d", "#b0b0b0", "#5f5f5f"),
    "classical": ("#d62728", "#ff7f0e", "#8c564b", "#e6ab02", "#7f2704", "#a6761d", "#fb9a99", "#c49c94",
                  "#fdbf6f", "#67000d"),
    "learned": ("#1f77b4", "#2ca02c", "#9467bd", "#17becf", "#08306b", "#005a32", "#54278f", "#00796b",
                "#2b8cbe", "#41ab5d", "#807dba", "#4eb3d3", "#1b9e77", "#386cb0", "#7570b3", "#393b79",
                "#008b8b", "#4daf4a", "#3288bd", "#5e3c99", "#6baed6", "#74c476", "#bcbddc", "#a1d99b",
                "#99d8c9", "#c6dbef", "#c7e9c0", "#9e9ac8"),
    "other": ("#cc33cc", "#e7298a", "#7a0177", "#f768a1", "#ae017e"),
}
_HUES = {"floor": (0.0, 0.0), "classical": (0.0, 50.0), "learned": (95.0, 265.0), "other": (300.0, 340.0)}
_TIME_COLUMNS = ("time", "follower_x", "follower_y", "target_x", "target_y", "recv_x", "recv_y", "F_u", "F_v",
                 "F_r", "along_track", "cross_track")
_OPTIONAL_TRACE_COLUMNS = ("own_ref_x", "own_ref_y", "est_x", "est_y", "packet_age")
_GENERATED = 48  # generated colours per family beside its palette (candidates for the policies drawn on a click)
_DISTINCT = 150.0  # a default-drawn policy's colour differs at least this much from the others on its tiers
_BIG = 1e100  # numbers of the leaderboard stay below this (their differences stay finite)
_BIG_TRACE = 1e9  # a recorded episode's positions [m], forces [N] and times [s] stay below this


@dataclass(frozen=True)
class _Style:
    """How a policy is drawn in every chart of the page."""

    color: str
    family: str
    rank: int  # legend order: families in _FAMILIES order, the best first
    shown: bool  # drawn by default (among the best SHOWN_PER_FAMILY of its family on some tier)

    @property
    def dash(self) -> str:
        return "dash" if self.family == "floor" else "solid"

    @property
    def group(self) -> str:
        """The plotly legend group of the policy's traces (an id: no text from the folder)."""
        return f"policy{self.rank}"

    @property
    def visible(self) -> bool | str:
        return True if self.shown else "legendonly"


def _rgb(color: str) -> tuple[int, int, int]:
    return int(color[1:3], 16), int(color[3:5], 16), int(color[5:7], 16)


def _distance(a: str, b: str) -> float:
    """Perceptual-ish distance of two colours ("redmean" weighted RGB)."""
    (r1, g1, b1), (r2, g2, b2) = _rgb(a), _rgb(b)
    rm = (r1 + r2) / 2
    return math.sqrt((2 + rm / 256) * (r1 - r2) ** 2 + 4 * (g1 - g2) ** 2 + (2 + (255 - rm) / 256) * (b1 - b2) ** 2)


def _generated(family: str, k: int) -> str:
    """The k-th colour of a family past its palette: hues spread over the family's range by the
    golden ratio, lightness alternating (unique for every k)."""
    import colorsys

    h0, h1 = _HUES[family]
    frac = (k * 0.6180339887) % 1.0
    light = (0.35, 0.5, 0.65)[k % 3]
    sat = 0.0 if family == "floor" else 0.65
    r, g, b = colorsys.hls_to_rgb((h0 + (h1 - h0) * frac) / 360.0, light, sat)
    color = f"#{round(r * 255):02x}{round(g * 255):02x}{round(b * 255):02x}"
    return color


def _policy_styles(board: pd.DataFrame, shown_per_family: int = SHOWN_PER_FAMILY) -> dict[str, _Style]:
    """One style per policy label of the (validated) leaderboard, computed once for the page.

    A policy's family comes from its kind (the first row's). Its rank within the family: its
    best place on any tier (by steady-state IQM), then its mean log ratio to each tier's best.
    It is drawn by default if that best place is among the first ``shown_per_family`` (floors:
    the oracle-parameter floor). Colours are unique: the policies drawn by default, family by family
    and best first, each take the first free colour of the family's palette (strong colours
    first) that differs by :data:`_DISTINCT` from the colours of the default-drawn policies (of
    any family but the floors, which are also told by their dashes and diamonds) on its tiers,
    else the most different of the next few; each of the others takes the free colour (of the
    palette or of :data:`_GENERATED` generated hues of the family) farthest from every colour
    already handed out on its tiers (all of them share the tables)."""
    m = "true_steady_mean_iqm"
    family = {}
    for p, k in zip(board["policy"], board["kind"], strict=True):
        family.setdefault(p, _FAMILY_OF_KIND.get(k, "other"))
    place: dict[str, int] = {}
    ratio: dict[str, list[float]] = {}
    tiers_of: dict[str, set[str]] = {}
    for tier, sub in board.groupby("tier", sort=False):
        best = sub.loc[sub["kind"] != "reference", m]
        best = float(best.min()) if best.notna().any() else float("nan")
        sub = sub.assign(_v=sub[m].fillna(np.inf)).sort_values("_v", kind="stable")
        counts: dict[str, int] = {}
        for p, v in zip(sub["policy"], sub[m], strict=True):
            f = family[p]
            place[p] = min(place.get(p, 1 << 30), counts.get(f, 0))
            counts[f] = counts.get(f, 0) + 1
            ok = np.isfinite(v) and v > 0 and np.isfinite(best) and best > 0
            ratio.setdefault(p, []).append(math.log(v / best) if ok else math.inf)
            tiers_of.setdefault(p, set()).add(str(tier))
    styles: dict[str, _Style] = {}
    drawn: dict[str, str] = {}
    chosen_all: dict[str, str] = {}  # every colour handed out so far (earlier families)
    for fi, f in enumerate(_FAMILIES):
        members = sorted((p for p in family if family[p] == f),
                         key=lambda p: (place[p], float(np.mean(ratio[p])) if ratio[p] else math.inf))
        # the palette first (the default-drawn policies take its strong colours), then generated hues
        # of the family, from which the policies drawn on a click pick the most distinct
        free = list(dict.fromkeys([*_PALETTES[f], *(_generated(f, k) for k in range(_GENERATED))]))
        extra = _GENERATED
        chosen: dict[str, str] = {}
        # floors: the oracle-parameter floor (the control floor, one to three decades below everything, is a
        # click away: drawn, it would squeeze the policies into a corner of every log axis)
        shown = [p for p in members if (p != CONTROL_FLOOR if f == "floor" else place[p] < shown_per_family)]
        for p in [*shown, *(q for q in members if q not in shown)]:
            if not free:
                while _generated(f, extra) in chosen.values():
                    extra += 1
                free.append(_generated(f, extra))
                extra += 1
            if p in shown:
                near = [c for q, c in drawn.items() if tiers_of[q] & tiers_of[p] and family[q] != "floor"]
                gap = [min((_distance(c, n) for n in near), default=math.inf) for c in free]
                pick = next((c for c, g in zip(free, gap, strict=True) if g >= _DISTINCT), None)
                if pick is None:
                    pick = max(zip(free[:6], gap[:6], strict=False), key=lambda cg: cg[1])[0]
            else:  # drawn on a click: the free colour farthest from every colour already on its tiers
                near = [c for q, c in {**chosen_all, **chosen}.items() if tiers_of[q] & tiers_of[p]
                        and family[q] != "floor"]
                gap = [min((_distance(c, n) for n in near), default=math.inf) for c in free]
                pick = free[int(np.argmax(gap))]
            free.remove(pick)
            chosen[p] = pick
            if p in shown:
                drawn[p] = pick
        for r, p in enumerate(members):
            styles[p] = _Style(chosen[p], f, fi * 10_000 + r, p in shown)
        chosen_all.update(chosen)
    return styles


def _txt(value: Any) -> str:
    """A value as plotly text: plotly renders a subset of HTML in labels and titles (links
    among it), so ``&``, ``<`` and ``>`` are written as entities (shown as themselves)."""
    return str(value).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


#: the widest tick label of the leaderboard chart [characters]: a longer policy name is wrapped
#: (with automargin, one very long label left the plot area no width and plotly.js threw "Something
#: went wrong with axis scaling")
LABEL_WIDTH = 70


def _wrapped(value: Any, width: int = LABEL_WIDTH) -> str:
    """:func:`_txt` of a label, wrapped at word boundaries into lines of at most ``width``
    characters (plotly's ``<br>``)."""
    import textwrap

    return "<br>".join(_txt(line) for line in textwrap.wrap(str(value), width, break_on_hyphens=False)) or _txt(value)


# --- checking what the folder holds ----------------------------------------------------------

_FILES = ("episodes.parquet", "leaderboard.csv", "benchmark.json", "traces.parquet")
_BOARD_TEXT = ("tier", "policy", "kind")
_BOARD_NUMBERS = tuple(f"{m}_{s}{b}" for m in ("true_steady_mean", "true_full_mean") for s in ("iqm", "mean")
                       for b in ("", "_lo", "_hi")) + ("termination_rate",)
_BOARD_COUNTS = ("runs", "episodes")
_BOARD_OPTIONAL_NUMBERS = ("true_steady_mean_iqm_change_pct", "poi", "poi_lo", "poi_hi", "paired_diff",
                           "paired_diff_lo", "paired_diff_hi", "paired_diff_base", "paired_diff_base_lo",
                           "paired_diff_base_hi", "paired_diff_filtered", "paired_diff_filtered_lo",
                           "paired_diff_filtered_hi", "gap_closed")
_BOARD_OPTIONAL_TEXT = ("best_classical", "base", "observation", "filtered_law")


def _inside(bench: Path) -> None:
    """Refuse a file of the benchmark that is a symbolic link out of the folder (a report reads
    only the folder's own files: a link could show any file of the machine on the page)."""
    root = bench.resolve()
    for name in _FILES:
        p = bench / name
        if not p.is_symlink():
            continue
        target = p.resolve()
        if not target.is_relative_to(root):
            raise ValueError(f"{p} is a symbolic link to {target}, outside {bench}: a report reads only the "
                             f"folder's own files (copy the file into the folder instead)")


def _too_deep(bench: Path) -> str:
    """Which file of the folder nests its JSON too deeply for Python's parser."""
    import pyarrow.parquet as pq

    texts: list[tuple[str, Any]] = [("benchmark.json", lambda: (bench / "benchmark.json").read_text())]
    texts.append(("leaderboard.csv", lambda: (bench / "leaderboard.csv").open().readline()[len("# provenance: "):]))
    for name in ("episodes.parquet", "traces.parquet"):
        texts.append((name, lambda n=name: (pq.read_schema(bench / n).metadata or {})
                      .get(b"auv_follow_provenance", b"null")))
    for name, read in texts:
        try:
            json.loads(read())
        except RecursionError:
            return name
        except Exception:  # noqa: BLE001 (only the nesting is asked here; load_result names other faults)
            continue
    return "benchmark.json"


def _row_text(df: pd.DataFrame, i: int) -> str:
    r = df.iloc[i]
    who = [f"{c} {str(r[c])[:60]!r}" for c in ("tier", "policy") if c in df]
    return f"row {i + 1}" + (f" ({', '.join(who)})" if who else "")


def _numbers(df: pd.DataFrame, col: str, where: str, *, bound: float = _BIG, finite: bool = False,
             whole: bool = False, nonneg: bool = False) -> pd.Series:
    """``df[col]`` as float64, refusing (ValueError naming ``where`` and the column) text, booleans,
    infinities, magnitudes of ``bound`` or more, NaN where ``finite``, fractions where ``whole``
    and negative values where ``nonneg``."""
    s = df[col]
    if pd.api.types.is_bool_dtype(s):
        raise ValueError(f"{where} column {col!r} holds booleans: numbers expected")
    v = pd.to_numeric(s, errors="coerce")
    if not pd.api.types.is_numeric_dtype(v) or pd.api.types.is_bool_dtype(v):
        raise ValueError(f"{where} column {col!r} is not numeric: numbers expected")
    v = v.astype(np.float64)
    text = v.isna() & s.notna()
    problems = [(text, "is not a number"), (~np.isfinite(v) & v.notna(), "is infinite"),
                (np.isfinite(v) & (v.abs() >= bound), f"is not below {bound:g} in magnitude")]
    if finite:
        problems.append((v.isna(), "is missing (NaN)"))
    if whole:
        problems.append((np.isfinite(v) & (v != np.floor(v)), "is not a whole number"))
    if nonneg:
        problems.append((v < 0, "is negative"))
    for bad, what in problems:
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise ValueError(f"{where} column {col!r} {what}: {str(s.iloc[i])[:60]!r} in {_row_text(df, i)}"
                             + (f" ({int(bad.sum())} rows in all)" if bad.sum() > 1 else ""))
    return v


def _texts(df: pd.DataFrame, col: str, where: str, *, required: bool = True) -> pd.Series:
    """``df[col]`` as text; a missing value is refused where ``required`` (else ``None``)."""
    s = df[col]
    miss = s.isna()
    if required and miss.any():
        i = int(np.flatnonzero(miss.to_numpy())[0])
        raise ValueError(f"{where} column {col!r} is empty in row {i + 1}: every row needs a {col}")
    return s.map(lambda x: None if pd.isna(x) else str(x)).astype(object)


def _seeds(df: pd.DataFrame, where: str) -> pd.Series:
    return _numbers(df, "seed", where, bound=2.0 ** 63, finite=True, whole=True, nonneg=True).astype(np.int64)


def _checked_board(board: pd.DataFrame, where: str) -> pd.DataFrame:
    """The leaderboard with every column the page uses checked and typed."""
    need = [c for c in (*_BOARD_TEXT, *_BOARD_COUNTS, *_BOARD_NUMBERS) if c not in board]
    if need:
        raise ValueError(f"{where} lacks columns {need} (the report shows them): write the folder again with "
                         f"`auv-follow benchmark`")
    out = pd.DataFrame(index=board.index)
    for c in _BOARD_TEXT:
        out[c] = _texts(board, c, where)
    for c in _BOARD_COUNTS:
        out[c] = _numbers(board, c, where, finite=True, whole=True, nonneg=True).astype(np.int64)
    for c in _BOARD_NUMBERS:  # errors [m] and a rate: never negative (and the charts' axes are logarithmic)
        out[c] = _numbers(board, c, where, nonneg=True)
    for c in _BOARD_OPTIONAL_NUMBERS:
        out[c] = _numbers(board, c, where) if c in board else np.nan
    for c in _BOARD_OPTIONAL_TEXT:
        out[c] = _texts(board, c, where, required=False) if c in board else None
    out = out.reset_index(drop=True)
    dup = out.duplicated(["tier", "policy"])
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0])
        raise ValueError(f"{where} has two rows for policy {out.loc[i, 'policy']!r} on tier {out.loc[i, 'tier']!r}")
    return out


def _checked_episodes(episodes: pd.DataFrame, where: str) -> pd.DataFrame:
    """The per-episode table with the columns the page uses checked and typed."""
    need = [c for c in ("tier", "policy", "seed", "terminated", "true_steady_mean") if c not in episodes]
    if need:
        raise ValueError(f"{where} lacks columns {need} (the breakdowns use them)")
    ep = episodes.copy()
    for c in ("tier", "policy"):
        ep[c] = _texts(episodes, c, where)
    ep["seed"] = _seeds(episodes, where)
    t = episodes["terminated"]
    if not pd.api.types.is_bool_dtype(t):
        def flag(x: Any) -> bool:
            return isinstance(x, (bool, np.bool_)) or (isinstance(x, (int, float, np.number)) and x in (0, 1))

        bad = ~t.map(flag).astype(bool)
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise ValueError(f"{where} column 'terminated' is not true/false (or 1/0): {str(t.iloc[i])[:60]!r} in "
                             f"{_row_text(episodes, i)}")
        ep["terminated"] = t.astype(bool)
    for c in ("true_steady_mean", "fail_error_m", "cond_latency_s", "cond_loss_prob"):
        if c in episodes:  # (errors, latencies and probabilities are never negative)
            ep[c] = _numbers(episodes, c, where, bound=_BIG_TRACE, nonneg=True)
    return ep


def _checked_traces(traces: pd.DataFrame | None, where: str) -> pd.DataFrame | None:
    """The recorded episodes with their keys checked (their values are checked per episode, when used)."""
    if traces is None or traces.empty:
        return None
    if not {"tier", "policy", "seed"} <= set(traces.columns):
        raise ValueError(f"{where} lacks columns {sorted({'tier', 'policy', 'seed'} - set(traces.columns))}")
    tr = traces.copy()
    for c in ("tier", "policy"):
        tr[c] = _texts(traces, c, where)
    tr["seed"] = _seeds(traces, where)
    return tr


def _checked_policies(prov: dict, where: str) -> dict[str, str | None]:
    """``{label: scripted controller name}`` of benchmark.json's ``config.policies``."""
    pols = prov["config"].get("policies", [])
    if pols is None:
        return {}
    if not isinstance(pols, list):
        raise ValueError(f"{where} config.policies is a {type(pols).__name__}: a list of policies expected")
    out: dict[str, str | None] = {}
    for p in pols:
        if isinstance(p, dict) and p.get("label") is not None:
            ctrl = p.get("controller")
            out[str(p["label"])] = ctrl if isinstance(ctrl, str) else None
    return out




def binned_breakdown(episodes: pd.DataFrame, condition: str, metric: str = "true_steady_mean",
                     bins: int = 6) -> pd.DataFrame:
    """IQM of ``metric`` per policy in equal-width bins of a drawn condition (pooled over the
    tiers in ``episodes``): columns policy, bin_center, iqm, episodes. Episodes without a value
    of the condition (NaN) are left out.

    Raises:
        ValueError: ``condition`` is not a column, or not finite numbers; ``bins`` is not a
            positive whole number.
    """
    from agents.benchmark.stats import iqm

    if condition not in episodes:
        raise ValueError(f"condition={condition!r} is not a column: valid conditions are "
                         f"{[c for c in episodes.columns if str(c).startswith('cond_')]}")
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise ValueError(f"bins={bins!r} is invalid: must be a whole number >= 1")
    v = _numbers(episodes, condition, f"condition={condition!r}:", bound=_BIG_TRACE)
    ep = episodes.assign(_score=scores(episodes, metric))[v.notna().to_numpy()]
    v = v[v.notna()]
    out = []
    if len(v):
        lo, hi = float(v.min()), float(v.max())
        edges = np.linspace(lo, hi if hi > lo else lo + 1e-9, bins + 1)
        ep["_bin"] = np.clip(np.digitize(v, edges[1:-1]), 0, bins - 1)
        for (pol, b), d in ep.groupby(["policy", "_bin"], sort=False):
            out.append({"policy": pol, "bin_center": 0.5 * (edges[b] + edges[b + 1]),
                        "iqm": float(iqm(d["_score"])), "episodes": len(d)})
    if not out:
        return pd.DataFrame(columns=["policy", "bin_center", "iqm", "episodes"])
    return pd.DataFrame(out).sort_values(["policy", "bin_center"]).reset_index(drop=True)


# --- figures -----------------------------------------------------------------------------

#: characters per line of a legend entry (the narrowest legend: three columns on a 1,400 px page at
#: plotly's 11 px font, about 6.5 px per character). Plotly does not wrap legend entries itself, and
#: unwrapped long labels ran past the figure's right edge. One width for every chart: a policy's
#: entry reads the same in each, and the page's colour checks match traces by name.
LEGEND_WIDTH = 48


def _legend_name(policy: Any) -> str:
    """A policy's legend entry: its label, wrapped at :data:`LEGEND_WIDTH`."""
    return _wrapped(policy, LEGEND_WIDTH)


def _legend(names: Sequence[str], columns: int = 3) -> tuple[dict, int]:
    """A legend under the plot in ``columns`` columns and the height it takes, for the entries
    ``names`` (wrapped by :func:`_legend_name`, in legend order: a row is as tall as its longest
    entry). The columns take 90 % of the figure's width: the legend starts at the plot area's left
    edge, which the axis labels push right, so full-width columns ran past the figure's right edge.
    ``maxheight`` 1: plotly caps a horizontal legend at half the figure's height by default and
    scrolls the rest out of sight."""
    lines = [str(n).count("<br>") + 1 for n in names]
    rows = [max(lines[i:i + columns]) for i in range(0, len(lines), columns)]
    return ({"orientation": "h", "yanchor": "top", "y": -0.08, "x": 0.0, "xanchor": "left",
             "entrywidth": 0.9 / columns, "entrywidthmode": "fraction", "font": {"size": 11},
             "traceorder": "normal", "maxheight": 1.0}, sum(22 + 15 * (k - 1) for k in rows) + 30)


def _policy_legend(policies: Iterable[str], styles: dict[str, _Style], columns: int = 3) -> tuple[dict, int]:
    """:func:`_legend` for these policies' entries, in legend order."""
    return _legend([_legend_name(p) for p in sorted(policies, key=lambda q: styles[q].rank)], columns)


def _buttons(visible: list, lift: float) -> list[dict]:
    """'best few' / 'all policies' buttons at the top left, ``lift`` (of the plot height) above the
    plot (they restyle every trace)."""
    return [{"type": "buttons", "direction": "left", "showactive": True, "x": 0.0, "xanchor": "left",
             "y": 1.0 + lift, "yanchor": "bottom", "pad": {"t": 0, "l": 0}, "font": {"size": 11}, "buttons": [
                 {"label": f"best {SHOWN_PER_FAMILY} of each family", "method": "restyle",
                  "args": [{"visible": visible}]},
                 {"label": "all policies", "method": "restyle", "args": [{"visible": [True] * len(visible)}]}]}]


def _fig_leaderboard(board: pd.DataFrame, styles: dict[str, _Style]):
    """One panel per tier, stacked (the labels need the width): one dot per policy at its IQM,
    in its colour, with its 95 % CI; the policies not drawn by default are a legend click away
    (a hidden policy's row closes up)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    tiers = list(dict.fromkeys(board["tier"]))
    m = "true_steady_mean"
    sizes = [int((board["tier"] == t).sum()) for t in tiers]
    fig = make_subplots(rows=len(tiers), cols=1, subplot_titles=[_txt(t) for t in tiers], row_heights=sizes,
                        vertical_spacing=min(0.3 / len(tiers), 0.07))
    seen: set[str] = set()
    for k, tier in enumerate(tiers, start=1):
        sub = board[board["tier"] == tier].assign(_v=lambda d: d[f"{m}_iqm"].fillna(np.inf))
        for _, r in sub.sort_values("_v", ascending=False, kind="stable").iterrows():
            p = r["policy"]
            st = styles[p]
            fig.add_trace(go.Scatter(
                x=[r[f"{m}_iqm"]], y=[_wrapped(p)], mode="markers", name=_legend_name(p), legendgroup=st.group,
                showlegend=p not in seen, legendrank=st.rank, visible=st.visible,
                marker={"color": st.color, "size": 11, "symbol": "diamond" if st.family == "floor" else "circle",
                        "line": {"color": "#222", "width": 0.5}},
                error_x={"type": "data", "symmetric": False, "array": [r[f"{m}_iqm_hi"] - r[f"{m}_iqm"]],
                         "arrayminus": [r[f"{m}_iqm"] - r[f"{m}_iqm_lo"]], "color": st.color, "thickness": 2,
                         "width": 5},
                customdata=[[r[f"{m}_iqm_lo"], r[f"{m}_iqm_hi"]]],
                hovertemplate=f"{_txt(tier)}: %{{y}}<br>IQM %{{x:.4f}} m [%{{customdata[0]:.4f}}, "
                              f"%{{customdata[1]:.4f}}]<extra></extra>"), row=k, col=1)
            seen.add(p)
        fig.update_xaxes(type="log", row=k, col=1)
        fig.update_yaxes(automargin=True, tickfont={"size": 11}, row=k, col=1)
    fig.update_xaxes(title_text="IQM of the steady-state error [m] (log scale)", row=len(tiers), col=1)
    # one column from the figure's left edge: the labels are long and the tick labels already take the
    # left part of the plot area, so two columns there overran the figure's right edge
    _, extra = _policy_legend(seen, styles, columns=1)
    legend = {"orientation": "v", "yanchor": "top", "x": 0.0, "xref": "container", "xanchor": "left",
              "font": {"size": 11}, "traceorder": "normal"}
    plot = 60 * len(tiers) + 19 * sum(sizes)
    legend["y"] = -60 / plot
    fig.update_layout(height=plot + extra + 110, legend=legend, margin={"l": 10, "r": 10, "t": 70, "b": extra + 40},
                      updatemenus=_buttons([tr.visible for tr in fig.data], 45 / plot))
    return fig


def _fig_breakdown(episodes: pd.DataFrame, condition: str, label: str, styles: dict[str, _Style]):
    """One panel per tier: the condition is binned within the tier (pooling tiers would plot
    the tier, not the condition)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    tiers = [str(t) for t in dict.fromkeys(episodes["tier"])] if "tier" in episodes else [""]
    fig = make_subplots(rows=1, cols=len(tiers), subplot_titles=[_txt(t) for t in tiers], horizontal_spacing=0.05)
    seen: set[str] = set()
    for c, tier in enumerate(tiers, start=1):
        ep = episodes[episodes["tier"].astype(str) == tier] if tier else episodes
        ep = ep[ep["policy"].isin(list(styles))]
        if condition not in ep or ep[condition].notna().sum() == 0:
            continue
        bd = binned_breakdown(ep, condition)
        groups = sorted(bd.groupby("policy", sort=False), key=lambda g: styles[g[0]].rank)
        for pol, d in groups:
            st = styles[pol]
            fig.add_trace(go.Scatter(x=d["bin_center"], y=d["iqm"], mode="lines+markers", name=_legend_name(pol),
                                     legendgroup=st.group, showlegend=pol not in seen, legendrank=st.rank,
                                     visible=st.visible,
                                     line={"color": st.color, "dash": st.dash, "width": 2},
                                     marker={"size": 6}, customdata=d["episodes"],
                                     hovertemplate=f"{_txt(pol)}<br>%{{x:.3g}}: %{{y:.4f}} m "
                                                   f"(%{{customdata}} episodes)<extra></extra>"), row=1, col=c)
            seen.add(pol)
        fig.update_xaxes(title_text=_txt(label), row=1, col=c)
        fig.update_yaxes(type="log", row=1, col=c)
    fig.update_yaxes(title_text="IQM of the steady-state error [m]", row=1, col=1)
    legend, extra = _policy_legend(seen, styles, columns=2)
    legend["y"] = -90 / 330
    fig.update_layout(height=330 + 150 + extra, legend=legend, margin={"l": 10, "r": 10, "t": 80, "b": extra + 70},
                      updatemenus=_buttons([tr.visible for tr in fig.data], 50 / 330))
    return fig


def _f4(s: pd.Series) -> np.ndarray:
    """A recorded time series as float32 (as traces.parquet stores it): half the page's bytes."""
    return s.to_numpy(np.float32)


def _fig_forces(runs: dict[str, pd.DataFrame], styles: dict[str, _Style], shown: Sequence[str]):
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    names = [("F_u", "N"), ("F_v", "N"), ("F_r", "N m")]
    fig = make_subplots(rows=3, cols=1, shared_xaxes=True, subplot_titles=[n for n, _ in names],
                        vertical_spacing=0.07)
    limits = next(iter(runs.values())).attrs.get("force_limits", (np.nan,) * 3)
    for pol, df in runs.items():
        for j, (n, _) in enumerate(names, start=1):
            fig.add_trace(go.Scatter(x=_f4(df["time"]), y=_f4(df[n]), name=_legend_name(pol),
                                     legendgroup=styles[pol].group,
                                     showlegend=j == 1, legendrank=styles[pol].rank,
                                     visible=True if pol in shown else "legendonly",
                                     line={"color": styles[pol].color, "width": 1.3},
                                     hovertemplate=f"{_txt(pol)}<br>t %{{x:.2f}} s: %{{y:.1f}}<extra></extra>"),
                          row=j, col=1)
    for j, ((n, unit), lim) in enumerate(zip(names, limits, strict=True), start=1):
        for sgn in (1, -1):
            fig.add_hline(y=sgn * lim, line_dash="dot", line_color="black", line_width=1, row=j, col=1)
        fig.update_yaxes(title_text=f"{n} [{unit}]", row=j, col=1)
    fig.update_xaxes(title_text="time [s]", row=3, col=1)
    legend, extra = _policy_legend(runs, styles)
    legend["y"] = -0.1
    fig.update_layout(height=640 + extra, legend=legend, margin={"l": 10, "r": 10, "t": 40, "b": extra + 30})
    return fig


def _fig_track(runs: dict[str, pd.DataFrame], styles: dict[str, _Style], shown: Sequence[str]):
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, subplot_titles=["along-track", "cross-track"],
                        vertical_spacing=0.1)
    for pol, df in runs.items():
        for j, col in enumerate(("along_track", "cross_track"), start=1):
            fig.add_trace(go.Scatter(x=_f4(df["time"]), y=_f4(df[col]), name=_legend_name(pol),
                                     legendgroup=styles[pol].group,
                                     showlegend=j == 1, legendrank=styles[pol].rank,
                                     visible=True if pol in shown else "legendonly",
                                     line={"color": styles[pol].color, "width": 1.3},
                                     hovertemplate=f"{_txt(pol)}<br>t %{{x:.2f}} s: %{{y:.3f}} m<extra></extra>"),
                          row=j, col=1)
    fig.update_yaxes(title_text="along [m] (+: ahead)", row=1, col=1)
    fig.update_yaxes(title_text="cross [m] (+: to port)", row=2, col=1)
    fig.update_xaxes(title_text="time [s]", row=2, col=1)
    legend, extra = _policy_legend(runs, styles)
    legend["y"] = -0.14
    fig.update_layout(height=520 + extra, legend=legend, margin={"l": 10, "r": 10, "t": 40, "b": extra + 30})
    return fig


def _fig_targets(df: pd.DataFrame, label: str, color: str):
    import plotly.graph_objects as go

    fig = go.Figure()
    fig.add_trace(go.Scatter(x=df["target_x"], y=df["target_y"], mode="lines", name="true target",
                             line={"color": "black", "width": 2}))
    fig.add_trace(go.Scatter(x=df["recv_x"], y=df["recv_y"], mode="markers", name="received (delayed) target",
                             marker={"size": 5, "color": "#7f7f7f", "symbol": "x-thin", "line": {"width": 1.5,
                                                                                              "color": "#555"}}))
    if "est_x" in df:
        fig.add_trace(go.Scatter(x=df["est_x"], y=df["est_y"], mode="lines", name=f"estimated target ({_txt(label)})",
                                 line={"color": color, "dash": "dot", "width": 2}))
    fig.add_trace(go.Scatter(x=df["follower_x"], y=df["follower_y"], mode="lines", name=f"follower ({_txt(label)})",
                             line={"color": color, "width": 1.5}))
    fig.update_layout(xaxis={"title": "x [m]", "constrain": "domain"}, yaxis_title="y [m]", height=720,
                      yaxis={"scaleanchor": "x", "scaleratio": 1},
                      legend={"orientation": "h", "yanchor": "bottom", "y": 1.02, "x": 0.0},
                      margin={"l": 10, "r": 10, "t": 40})
    return fig


def _fig_replay(df: pd.DataFrame, color: str, every: int = 10, trail_s: float = 20.0):
    import plotly.graph_objects as go

    idx = list(range(0, len(df), every)) + ([len(df) - 1] if (len(df) - 1) % every else [])
    dt = float(df["time"].iloc[1] - df["time"].iloc[0]) if len(df) > 1 else 1.0
    trail = max(1, int(round(trail_s / dt)))

    def moving(k: int) -> list:
        d = df.iloc[max(0, k - trail): k + 1]
        last = df.iloc[k]
        return [go.Scatter(x=d["recv_x"], y=d["recv_y"], mode="markers",
                           marker={"size": 5, "color": "#555", "symbol": "x-thin", "line": {"width": 1.5,
                                                                                         "color": "#555"}},
                           name=f"received target (last {trail_s:g} s)"),
                go.Scatter(x=[last["target_x"], last["follower_x"], last["recv_x"]],
                           y=[last["target_y"], last["follower_y"], last["recv_y"]], mode="markers",
                           marker={"size": [13, 13, 11], "color": ["black", color, "#555"],
                                   "symbol": ["triangle-up", "circle", "x"]},
                           name="now: true target / follower / received")]

    static = [go.Scatter(x=df["target_x"], y=df["target_y"], mode="lines", line={"color": "#bbbbbb"},
                         name="true target path"),
              go.Scatter(x=df["follower_x"], y=df["follower_y"], mode="lines", line={"color": color, "width": 1},
                         opacity=0.45, name="follower path")]
    frames = [go.Frame(data=moving(k), traces=[2, 3], name=f"{df['time'].iloc[k]:.1f}") for k in idx]
    fig = go.Figure(data=static + moving(idx[0]), frames=frames)
    steps = [{"args": [[f.name], {"frame": {"duration": 0, "redraw": True}, "mode": "immediate"}],
              "label": f.name, "method": "animate"} for f in frames]
    fig.update_layout(
        height=720, xaxis={"title": "x [m]", "constrain": "domain"}, margin={"l": 10, "r": 10, "t": 40},
        yaxis={"title": "y [m]", "scaleanchor": "x", "scaleratio": 1},
        legend={"orientation": "h", "yanchor": "bottom", "y": 1.02, "x": 0.0},
        updatemenus=[{"type": "buttons", "showactive": False, "x": 0.0, "y": -0.12, "buttons": [
            {"label": "play", "method": "animate",
             "args": [None, {"frame": {"duration": 50, "redraw": True}, "fromcurrent": True}]},
            {"label": "pause", "method": "animate",
             "args": [[None], {"frame": {"duration": 0, "redraw": False}, "mode": "immediate"}]}]}],
        # 120 step labels overlap: hide them (transparent font), show the current time instead
        sliders=[{"steps": steps, "x": 0.12, "len": 0.88, "y": -0.05, "font": {"color": "rgba(0,0,0,0)"},
                  "currentvalue": {"prefix": "t = ", "suffix": " s", "xanchor": "right",
                                   "font": {"color": "#333", "size": 13}}}])
    return fig


# --- page ----------------------------------------------------------------------------------

def _columns_html(board: pd.DataFrame, gap: bool, has_base: bool, has_filtered: bool = False) -> str:
    """What each column of the leaderboard tables means (shown above them)."""
    items = [
        ("policy", "a scripted controller, or a learned method (its training runs pooled). The square beside it "
                   "is its colour in every chart of this page. Bold row (shaded): the tier's best classical "
                   "baseline, the scripted controller with the lowest steady-state IQM; grey italics: the floors, "
                   "reference rows that are not policies."),
        ("kind", "classical (a scripted controller of this package), learned (trained agents), external (a "
                 "controller given as module:Class) or reference (a floor)."),
        ("runs x episodes", "training runs pooled x test episodes per run (one per test seed of the tier)."),
        ("steady IQM [m] [95 % CI]", "the score of an episode is its true-reference tracking error, the mean "
                                     "distance of the follower from where it should be, over the steady-state "
                                     "window t >= 10 s (an episode that lost the target scores the loss "
                                     "threshold). IQM: the interquartile mean over the episodes (mean of the "
                                     "middle 50 %, robust to a few bad episodes), with its 95 % stratified-"
                                     "bootstrap confidence interval (strata: training runs). Lower is better; "
                                     "the rows are sorted by it."),
        ("steady mean [m] [95 % CI]", "the plain mean of the same per-episode scores (sensitive to bad episodes)."),
        ("full IQM [m] [95 % CI]", "the IQM over the whole episode, including the start, where every follower "
                                   "first closes its initial offset."),
        ("full mean [m] [95 % CI]", "the mean over the whole episode."),
        ("IQM vs best classical [%]", "steady IQM / the best classical's steady IQM - 1, in percent: negative is "
                                      "better than the best classical."),
        ("paired diff vs best classical [m] [95 % CI]", "the mean over the test seeds of (this policy's steady-"
                                                        "state error - the best classical's on the same seed), a "
                                                        "method's runs averaged per seed, with a 95 % bootstrap CI "
                                                        "over seeds: negative is better, and a CI that excludes 0 "
                                                        "is a difference beyond chance."),
    ]
    if has_base:
        items.append(("paired diff vs its base [m] [95 % CI]", "for a residual agent (a learned correction on top "
                                                               "of a scripted controller): the same paired "
                                                               "difference against its own base controller; "
                                                               "obs: what its observation carries (raw: the env's "
                                                               "fields and the base action; estimator: also a "
                                                               "target filter's estimate; learned estimator: a "
                                                               "learned estimate of the target feeding the base's "
                                                               "own law, no learned action)."))
    if has_filtered:
        items.append(("paired diff vs its base's law on its observation's filter [m] [95 % CI]",
                      "for a residual whose observation carries a target filter its base lacks: the paired "
                      "difference against the same control law run on that filter. Most of a gain over the base "
                      "that this column does not show is the filter's information, not learned control."))
    items += [
        ("P(better) [95 % CI]", "the probability that an episode of this policy has a lower steady-state error "
                                "than an episode of the best classical (rliable's probability of improvement, "
                                "unpaired; ties count half): 0.5 is no difference."),
        ("terminated [%]", "the share of episodes that ended early because the follower lost the target."),
    ]
    if gap:
        ref = board[board["policy"] == INFORMATION_FLOOR]
        example = ""
        rows = []
        for tier, sub in board.groupby("tier", sort=False):
            name = _gap_floor(sub)
            floor = sub.loc[sub["policy"] == name, "true_steady_mean_iqm"]
            best = sub.loc[sub["gap_closed"] == 0.0, "true_steady_mean_iqm"]
            worst = sub["gap_closed"].min()
            if len(floor) and len(best) and np.isfinite(worst):
                rows.append((float(best.iloc[0]) - float(floor.iloc[0]), str(tier), float(best.iloc[0]),
                             float(floor.iloc[0]), float(worst), name))
        if len(ref) and rows:
            g, tier, b, f, worst, name = min(rows)
            example = (f" On {html.escape(tier)} the best generic classical ({b:.4f} m) is only {g:.4f} m above the "
                       f"{html.escape(name)} ({f:.4f} m), so a policy d metres worse than the best classical gets "
                       f"-d / {g:.4f}: the lowest value there is {worst:.2f}.")
        items.append(("gap closed [-]", "(best generic classical IQM - this IQM) / (best generic classical IQM - "
                                        "floor IQM): how much of the gap between the best generic "
                                        "classical baseline (on a Leader tier: not the model-aware particle "
                                        "filter, which knows the generator) and the floor named in the column's "
                                        "head a policy closes. The floor is the tier-prior floor where it "
                                        "converged (a follower who knows the tier's generator and published "
                                        "ranges, not the episode's draws: a floor a follower could reach), else "
                                        "the oracle-parameter floor (the error of an ideal estimate from the "
                                        "packets received by a filter that knows each episode's drawn parameters, "
                                        "which no follower can beat); where both exist, a second column measures "
                                        "against the oracle-parameter floor. 0 is the best generic classical, 1 "
                                        "reaches the floor. It is measured in units of "
                                        "that gap, so where the gap is small a policy that is worse than the "
                                        "best classical gets a very negative value: it says how many gaps "
                                        "worse it is, not that anything is broken." + example +
                                        " It can exceed 1 slightly: the floor is an expectation per episode "
                                        "while a policy's scores are realisations that scatter about theirs."))
    return ("<dl class='columns'>" + "".join(f"<dt>{html.escape(k)}</dt><dd>{v}</dd>" for k, v in items)
            + "</dl>")


def _gap_floor(sub: pd.DataFrame) -> str:
    """The floor a tier's ``gap_closed`` is measured against (older folders: the oracle-parameter floor)."""
    name = sub["gap_floor"].iloc[0] if "gap_floor" in sub and len(sub) else None
    return name if isinstance(name, str) and name else INFORMATION_FLOOR


def _table_html(board: pd.DataFrame, styles: dict[str, _Style]) -> str:
    m0 = "true_steady_mean"
    has_base = board["base"].notna().any()
    has_filtered = board["filtered_law"].fillna("").astype(bool).any()
    gap = board["gap_closed"].notna().any()  # floors present (agents/benchmark/floors.py)
    parts = [_columns_html(board, gap, has_base, has_filtered)]
    for tier, sub in board.groupby("tier", sort=False):
        best = sub["best_classical"].iloc[0]
        parts.append(f"<h3>{html.escape(str(tier))}" + (f" (best classical: {html.escape(str(best))})" if
                                                        isinstance(best, str) else "") + "</h3>")
        head = ["policy", "kind", "runs x episodes", "steady IQM [m] [95 % CI]", "steady mean [m] [95 % CI]",
                "full IQM [m] [95 % CI]", "full mean [m] [95 % CI]", "IQM vs best classical [%]",
                "paired diff vs best classical [m] [95 % CI]"]
        head += ["paired diff vs its base [m] [95 % CI]"] if has_base else []
        head += ["paired diff vs its base's law on its observation's filter [m] [95 % CI]"] if has_filtered else []
        head += ["P(better) [95 % CI]", "terminated [%]"]
        gap_floor = _gap_floor(sub)
        both = (gap and gap_floor != INFORMATION_FLOOR and "gap_closed_oracle" in sub
                and sub["gap_closed_oracle"].notna().any())
        head += [f"gap closed [-] ({gap_floor})"] if gap else []
        head += [f"gap closed [-] ({INFORMATION_FLOOR})"] if both else []
        parts.append("<table class='leaderboard' data-tier='" + html.escape(str(tier)) + "'><thead><tr>" +
                     "".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>")
        sub = sub.assign(_v=sub[f"{m0}_iqm"].fillna(np.inf)).sort_values("_v", kind="stable")
        for _, r in sub.iterrows():
            def ci(m: str, stat: str, row: pd.Series = r) -> str:
                v, lo, hi = row[f"{m}_{stat}"], row[f"{m}_{stat}_lo"], row[f"{m}_{stat}_hi"]
                return "-" if not np.isfinite(v) else f"{v:.4f} [{lo:.4f}, {hi:.4f}]"

            def signed(v: float, lo: float, hi: float) -> str:
                return "-" if not np.isfinite(v) else f"{v:+.4f} [{lo:+.4f}, {hi:+.4f}]"

            chg = r[f"{m0}_iqm_change_pct"]
            cells = [r["kind"], f"{r['runs']} x {r['episodes'] // max(int(r['runs']), 1)}",
                     ci(m0, "iqm"), ci(m0, "mean"), ci("true_full_mean", "iqm"), ci("true_full_mean", "mean"),
                     "-" if not np.isfinite(chg) else f"{chg:+.1f} %",
                     "-" if r["policy"] == best else signed(r["paired_diff"], r["paired_diff_lo"],
                                                            r["paired_diff_hi"])]
            if has_base:
                d = signed(r["paired_diff_base"], r["paired_diff_base_lo"], r["paired_diff_base_hi"])
                obs = f"; obs {r['observation']}" if r["observation"] else ""
                cells.append(f"{d} (base {r['base']}{obs})" if r["base"] and d != "-" else "-")
            if has_filtered:
                d = signed(r["paired_diff_filtered"], r["paired_diff_filtered_lo"], r["paired_diff_filtered_hi"])
                cells.append(f"{d} ({r['filtered_law']})" if r["filtered_law"] and d != "-" else "-")
            cells += ["-" if not np.isfinite(r["poi"]) else f"{r['poi']:.2f} [{r['poi_lo']:.2f}, {r['poi_hi']:.2f}]",
                      "-" if not np.isfinite(r["termination_rate"]) else f"{100 * r['termination_rate']:.0f} %"]
            if gap:
                cells.append("-" if not np.isfinite(r["gap_closed"]) else f"{r['gap_closed']:.2f}")
            if both:
                cells.append("-" if not np.isfinite(r["gap_closed_oracle"]) else f"{r['gap_closed_oracle']:.2f}")
            cls = "leaderboard-row best" if r["policy"] == best else "leaderboard-row"
            cls += " reference" if r["kind"] == "reference" else ""
            swatch = f"<span class='swatch' style='background:{styles[r['policy']].color}'></span>"
            parts.append(f"<tr class='{cls}' data-policy='{html.escape(str(r['policy']), quote=True)}'>"
                         f"<td>{swatch}{html.escape(str(r['policy']))}</td>" +
                         "".join(f"<td>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
        parts.append("</tbody></table>")
    return "\n".join(parts)


_CSS = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1400px;padding:0 1em;color:#222}
h2{margin-top:1.6em;border-bottom:1px solid #ddd;padding-bottom:.2em}
table{border-collapse:collapse;margin-bottom:1em;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px}
td:first-child{min-width:16em}tr.best{font-weight:bold;background:#fff4e5}tr.reference{color:#666;font-style:italic}
th{background:#f3f3f3}pre{background:#f7f7f7;padding:1em;overflow:auto;font-size:11px}
.note{color:#444;font-size:14px;max-width:75em}.swatch{display:inline-block;width:.8em;height:.8em;margin-right:.45em;
border-radius:2px;vertical-align:baseline}dl.columns{font-size:13px;max-width:80em;display:grid;
grid-template-columns:max-content auto;gap:.25em 1em}dl.columns dt{font-weight:bold}dl.columns dd{margin:0}
nav a{margin-right:1em}nav{font-size:14px}"""


def _stored_episode(traces: pd.DataFrame | None, tier: str, label: str, seed: int,
                    where: str = "traces.parquet") -> pd.DataFrame | None:
    """The recorded per-step episode of ``label`` on ``tier`` / ``seed`` from ``traces.parquet``,
    its values checked (ValueError naming the file, the column and the episode)."""
    if traces is None or traces.empty or not {"tier", "policy", "seed"} <= set(traces.columns):
        return None
    d = traces[(traces["tier"].astype(str) == tier) & (traces["policy"].astype(str) == label)
               & (traces["seed"] == seed)]
    if d.empty:
        return None
    d = d.drop(columns=["tier", "policy", "seed"]).reset_index(drop=True)
    what = f"{where} (episode of {label!r} on {tier}, seed {seed})"
    lacks = [c for c in _TIME_COLUMNS if c not in d]
    if lacks:
        raise ValueError(f"{what} lacks columns {lacks}")
    for c in (*_TIME_COLUMNS, *(c for c in _OPTIONAL_TRACE_COLUMNS if c in d)):
        d[c] = _numbers(d, c, what, bound=_BIG_TRACE, finite=c == "time")
    if len(d) > 1 and not (np.diff(d["time"].to_numpy()) > 0).all():
        raise ValueError(f"{what} column 'time' does not increase from step to step")
    empty = [c for c in _OPTIONAL_TRACE_COLUMNS if c in d and d[c].isna().all()]
    return d.drop(columns=empty)


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a new temporary file beside it (created exclusively,
    so a file or link already there under any name is never written through), then rename it
    into place: an interrupted or failed write never leaves half a page, and a link at ``path``
    itself is replaced, not followed.

    Raises:
        ValueError: the page cannot be written (full disk, no permission, ...): names ``path``.
    """
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".partial")
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # as an ordinary new file (mkstemp makes it private)
        os.replace(tmp, path)
    except OSError as exc:
        raise ValueError(f"cannot write the report {path}: {exc.strerror or exc} (the previous page, if any, "
                         f"is unchanged)") from None
    finally:
        if tmp is not None and os.path.lexists(tmp):
            os.unlink(tmp)


def write_report(bench_dir: str | Path = "results/benchmark", out: str | Path | None = None, *,
                 replay_policy: str | None = None, replay_tier: str | None = None, replay_seed: int | None = None,
                 time_policies: Sequence[str] | None = None) -> Path:
    """Write the HTML report of a benchmark directory and return its path.

    Built from the stored tables alone (see the module docstring): never loads a model file,
    and reads only the folder's own files.

    Args:
        bench_dir: a directory written by :func:`agents.benchmark.benchmark`.
        out: HTML file (default ``<bench_dir>/report.html``).
        replay_policy: policy label of the replay (default: the best policy on the replay tier
            with a recorded episode).
        replay_tier: tier of the time plots and the replay (default: Hard if benchmarked,
            else the last tier).
        replay_seed: test seed of the replay (default: the seed of the recorded episodes, else
            the tier's first benchmarked seed).
        time_policies: policies drawn in the force / track plots (default: the best classical,
            the best learned and PROPOSED where present and recorded); the other recorded
            policies of the tier are there too, hidden until clicked in the legend.

    Raises:
        FileNotFoundError: no benchmark in ``bench_dir``.
        TypeError: an argument of the wrong type.
        ValueError: unknown policy, tier or seed (names the valid ones); a learned policy asked
            for without a recorded episode; files that are corrupt, malformed (names the file
            and the column), from different runs, or symbolic links out of the folder; ``out``
            is a directory.
    """
    import plotly.offline

    from controllers import make_controller

    if not isinstance(bench_dir, (str, os.PathLike)):
        raise TypeError(f"bench_dir={bench_dir!r} is invalid: must be a path (str or Path)")
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"out={out!r} is invalid: must be a path (str or Path) or None")
    for arg, v in (("replay_policy", replay_policy), ("replay_tier", replay_tier)):
        if v is not None and not isinstance(v, str):
            raise TypeError(f"{arg}={v!r} is invalid: must be a str or None")
    if replay_seed is not None and (isinstance(replay_seed, bool) or not isinstance(replay_seed, (int, np.integer))):
        raise TypeError(f"replay_seed={replay_seed!r} is invalid: must be a whole number (int) or None")
    if time_policies is not None:
        if isinstance(time_policies, str) or not all(isinstance(p, str) for p in time_policies):
            raise TypeError(f"time_policies={time_policies!r} is invalid: must be a list of policy labels (str)")
        time_policies = list(time_policies)
    bench = Path(bench_dir)
    path = Path(out) if out is not None else bench / "report.html"
    if path.is_dir():
        raise ValueError(f"out={str(path)!r} is a directory: give the path of an HTML file")
    _inside(bench)
    try:
        res = load_result(bench)
    except RecursionError:
        name = _too_deep(bench)
        raise ValueError(f"{bench / name} nests its JSON too deeply to be read: it is not a file written by "
                         f"`auv-follow benchmark`") from None
    board = _checked_board(res.leaderboard, str(bench / "leaderboard.csv"))
    episodes = _checked_episodes(res.episodes, str(bench / "episodes.parquet"))
    traces = _checked_traces(res.traces, str(bench / "traces.parquet"))
    prov = res.provenance
    controllers_by_label = _checked_policies(prov, str(bench / "benchmark.json"))
    try:
        prov_text = json.dumps(prov, indent=1, default=str)
    except (RecursionError, ValueError) as exc:
        raise ValueError(f"{bench / 'benchmark.json'} cannot be shown: {type(exc).__name__}") from None
    styles = _policy_styles(board)
    tiers = [str(t) for t in dict.fromkeys(board["tier"])]
    if not tiers:
        raise ValueError(f"{bench / 'leaderboard.csv'} has no rows")
    tier = replay_tier if replay_tier is not None else ("Hard" if "Hard" in tiers else tiers[-1])
    if tier not in tiers:
        raise ValueError(f"replay_tier={replay_tier!r} was not benchmarked: valid tiers are {tiers}")
    try:
        _, env_id = resolve_tier(tier)
    except ValueError as exc:
        if replay_tier is not None:
            raise
        raise ValueError(f"{bench / 'leaderboard.csv'} column 'tier': {exc}") from None
    sub = board[(board["tier"] == tier) & (board["kind"] != "reference")]
    sub = sub.assign(_v=sub["true_steady_mean_iqm"].fillna(np.inf)).sort_values("_v", kind="stable")
    labels = [str(p) for p in sub["policy"]]  # (floors are references: nothing to replay)
    kinds = dict(zip(labels, sub["kind"], strict=True))
    seeds = sorted(int(x) for x in episodes.loc[episodes["tier"] == tier, "seed"].unique())
    if not seeds:
        raise ValueError(f"{bench / 'episodes.parquet'} has no episodes of tier {tier!r}")
    traced = sorted(int(x) for x in traces.loc[traces["tier"] == tier, "seed"].unique()) \
        if traces is not None else []
    seed = int(replay_seed) if replay_seed is not None else (traced[0] if traced else seeds[0])
    if seed not in seeds:
        raise ValueError(f"replay_seed={replay_seed!r} was not benchmarked on {tier}: valid seeds are "
                         f"{seeds[0]}..{seeds[-1]} ({len(seeds)} seeds)")
    probe = gym.make(env_id)
    task_spec = probe.unwrapped.task_spec
    probe.close()
    limits = tuple(float(v) for v in task_spec.force_limits)
    scripted = set(_controllers())
    cache: dict[str, pd.DataFrame | None] = {}
    where = str(bench / "traces.parquet")

    def episode(label: str, rerun: bool = True) -> pd.DataFrame | None:
        """Recorded episode, or a scripted controller of this package re-run; never a model file."""
        if label not in cache or (cache[label] is None and rerun):
            df = _stored_episode(traces, tier, label, seed, where)
            ctrl = controllers_by_label.get(label)
            if df is None and rerun and kinds.get(label) == "classical" and ctrl in scripted:
                df = rollout_episode(make_controller(ctrl, task_spec), env_id, seed)
            if df is not None:
                df.attrs["force_limits"] = limits
            cache[label] = df
        return cache[label]

    def refuse(arg: str, label: str) -> None:
        have = [p for p in labels if episode(p) is not None]
        raise ValueError(f"{arg}={label!r} has no recorded episode on {tier}, seed {seed} in {where} (a report "
                         f"never loads model files): policies with one are {have}")

    if replay_policy is not None:
        if replay_policy not in labels:
            raise ValueError(f"replay_policy={replay_policy!r} is unknown: valid policies are {labels}")
        if episode(replay_policy) is None:
            refuse("replay_policy", replay_policy)
        policy = replay_policy
    else:
        policy = next((p for p in labels if episode(p) is not None), None)
    if time_policies is None:
        picks = [[p for p in labels if kinds[p] == "classical" and episode(p) is not None][:1],
                 [p for p in labels if kinds[p] == "learned" and episode(p) is not None][:1],
                 [p for p in ("PROPOSED",) if p in labels and episode(p) is not None]]
        time_policies = list(dict.fromkeys(p for group in picks for p in group))
    for p in time_policies:
        if p not in labels:
            raise ValueError(f"time_policies has {p!r}: valid policies are {labels}")
        if episode(p) is None:
            refuse("time_policies", p)
    missing = [p for p in labels if kinds[p] == "learned" and episode(p) is None]
    runs = {p: episode(p) for p in dict.fromkeys([*time_policies, *([policy] if policy else [])])}
    # the tier's other recorded episodes: in the time plots too, hidden until clicked (no re-runs)
    timed = {p: runs[p] for p in time_policies}
    timed.update({p: df for p in labels if p not in timed and (df := episode(p, rerun=False)) is not None})
    timed = dict(sorted(timed.items(), key=lambda kv: styles[kv[0]].rank))
    est_label = next((p for p in runs if "est_x" in runs[p]), policy)
    few = (f"the best {SHOWN_PER_FAMILY} of each family on each tier and the oracle-parameter floor (the control "
           f"floor lies one to three decades below and is in the legend)")
    click = ("click a legend entry to show or hide that policy, double-click it to show it alone; the buttons "
             "above the chart show all policies or the best few again")
    sections: list[tuple[str, str, str, Any]] = [
        ("leaderboard-chart", "Steady-state error by policy",
         f"The steady-state IQM of each policy with its 95 % CI (log scale), one panel per tier; drawn: {few}. "
         f"The others are listed in the legend: {click}.", _fig_leaderboard(board, styles)),
        ("latency", "Error vs latency",
         f"The steady-state error against the drawn packet latency: the latency is cut into 6 equal-width bins "
         f"within each tier, one point per bin (the IQM of its episodes). Drawn: {few}; {click}.",
         _fig_breakdown(episodes, "cond_latency_s", "latency [s]", styles)),
        ("loss", "Error vs loss rate",
         f"The same against the drawn packet loss probability. Drawn: {few}; {click}.",
         _fig_breakdown(episodes, "cond_loss_prob", "packet loss probability", styles)),
    ]
    if time_policies:
        shown = ", ".join(html.escape(p) for p in time_policies)
        sections += [
            ("forces", "Forces",
             f"Forces over time on {html.escape(tier)}, seed {seed} (dotted: the force limits). Drawn: {shown}; "
             f"the tier's other recorded policies are in the legend, {click.split(';')[0]}.",
             _fig_forces(timed, styles, time_policies)),
            ("track", "Along- and cross-track error",
             "The follower's error from the true reference in the true target's heading frame, same episode "
             "and policies as above.", _fig_track(timed, styles, time_policies))]
    if policy is not None:
        sections += [
            ("targets", "Delayed, estimated and true target",
             f"{html.escape(tier)}, seed {seed}: the true target (black), what the follower received (grey "
             f"crosses: delayed and noisy, with gaps where packets were lost), the target {html.escape(est_label)} "
             f"estimated (its own reference minus the offset p_d, dotted) and its path (solid), in its colour.",
             _fig_targets(runs[est_label], est_label, styles[est_label].color)),
            ("replay", "Episode replay",
             f"Replay: {html.escape(policy)} on {html.escape(tier)}, seed {seed}. Press play or drag the slider. The "
             f"follower is drawn in its colour, the true target in black, the received packets of the last 20 s "
             f"as grey crosses.", _fig_replay(runs[policy], styles[policy].color))]
    note = ("" if not missing else
            f" Learned policies without a recorded episode in traces.parquet (left out of the time plots and the "
            f"replay; a report never loads model files): {html.escape(', '.join(missing))}.")
    families = [f for f in _FAMILIES if any(s.family == f for s in styles.values())]
    body = [f"<h1>auv-follow benchmark</h1><p class='note'>Tiers: {html.escape(', '.join(tiers))}. "
            f"Time plots and replay: {html.escape(tier)} ({html.escape(env_id)}), test seed {seed}. Every number is "
            f"reproduced by the command in the provenance below.{note}</p>",
            "<p class='note'>Each policy has one colour, the same in every chart and beside its name in the "
            f"tables: {html.escape(', '.join(_FAMILY_NAMES[f] for f in families))}; the best of each family have "
            "the strongest, most distinct colours.</p>",
            "<nav>" + "".join(f"<a href='#{a}'>{html.escape(t)}</a>" for a, t in
                              [("leaderboard", "Leaderboard"), *((s[0], s[1]) for s in sections),
                               ("provenance", "Provenance")]) + "</nav>",
            "<h2 id='leaderboard'>Leaderboard</h2><p class='note'>One table per tier, sorted by the steady-state "
            "IQM (best first). The columns:</p>", _table_html(board, styles)]
    for k, (anchor, title, caption, fig) in enumerate(sections):
        body.append(f"<h2 id='{anchor}'>{html.escape(title)}</h2><p class='note'>{caption}</p>")
        body.append(fig.to_html(full_html=False, include_plotlyjs=False, div_id=f"fig{k}",
                                config={"displaylogo": False, "responsive": True}))
    body.append("<h2 id='provenance'>Provenance</h2><details><summary>configuration, versions and the command "
                "(click to expand)</summary><pre>" + html.escape(prov_text) + "</pre></details>")
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>auv-follow benchmark</title>"
            "<link rel='icon' href='data:,'>"
            f"<style>{_CSS}</style><script type='text/javascript'>{plotly.offline.get_plotlyjs()}</script>"
            "</head><body>" + "\n".join(body) + "</body></html>")
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomic(path, page)
    return path
