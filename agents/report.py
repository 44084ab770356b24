"""One self-contained HTML page from a benchmark directory (``auv-follow report``).

The page embeds plotly.js inline (no CDN, no server: open the file) and shows

* the leaderboard (the table of :func:`agents.benchmark.leaderboard_markdown`, as HTML, and a
  bar chart of the steady-state IQM with its 95 % CI per tier);
* breakdowns over the drawn conditions: steady-state error vs latency and vs loss rate
  (one panel per tier, binned within the tier, IQM per bin);
* one episode per policy on the replay tier: forces over time with the force limits, and
  along-track / cross-track error over time (error of the follower from the true reference,
  in the true target's heading frame);
* the delayed (received), estimated (the controller's own reference minus the offset p_d)
  and true target on one episode of the replay tier (Hard when it was benchmarked);
* an episode replay (play / slider): follower, true target and what the follower received,
  for a chosen policy and seed.

The page is built from the stored tables alone: the time plots and the replay come from the
benchmark's ``traces.parquet`` (one episode per tier and policy, recorded when the benchmark
ran). Building a report never loads a ``model.zip`` (an SB3 file can run code when loaded):
where a folder has no trace of a policy, a scripted controller of this package is re-run by
name (deterministic: same seed, same episode) and a learned policy is left out of the time
plots, with a note. Every value read from the folder is escaped before it reaches the page.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd

from agents.benchmark import (
    LEADERBOARD_METRICS,
    _controllers,
    load_result,
    resolve_tier,
    scores,
)
from auv_follow_env.layout import OBS_INDEX_V1

__all__ = ["write_report", "rollout_episode", "binned_breakdown"]

_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf")


_PALETTE: dict[str, str] = {}


def _color(policy: Any) -> str:
    """The colour of a policy, the same in every figure of the page (set by :func:`write_report`
    from the leaderboard's order; unknown labels get the next free colour)."""
    key = str(policy)
    if key not in _PALETTE:
        _PALETTE[key] = _COLORS[len(_PALETTE) % len(_COLORS)]
    return _PALETTE[key]


def _txt(value: Any) -> str:
    """A value as plotly text: plotly renders a subset of HTML in labels and titles (links
    among it), so ``&``, ``<`` and ``>`` are written as entities (shown as themselves)."""
    return str(value).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def rollout_episode(policy: Any, env_id: str, seed: int) -> pd.DataFrame:
    """One episode, per step: time, follower pose, true target and reference, the target the
    follower received (world frame), the policy's own reference (if it has one), forces and
    along-/cross-track error."""
    env = gym.make(env_id)
    spec = env.unwrapped.task_spec
    limits = np.asarray(spec.force_limits)
    obs, info = env.reset(seed=int(seed))
    if hasattr(policy, "reset"):
        policy.reset()
    rows, start = [], True
    i = OBS_INDEX_V1
    while True:
        action, _ = policy.predict(obs, episode_start=np.array([start]), deterministic=True)
        start = False
        obs, _, term, trunc, info = env.step(action)
        x, y, psi = (float(v) for v in info["follower_pose"])
        tx, ty, tpsi = (float(v) for v in info["true_target"][:3])
        rx, ry = (float(v) for v in info["true_reference"][:2])
        c, s = np.cos(psi), np.sin(psi)
        has = obs.shape[-1] <= i["has_packet"] or obs[i["has_packet"]] > 0.5
        dx, dy = float(obs[i["target_dx"]]), float(obs[i["target_dy"]])
        row = {"time": float(info["time"]), "follower_x": x, "follower_y": y, "follower_psi": psi,
               "target_x": tx, "target_y": ty, "target_psi": tpsi, "ref_x": rx, "ref_y": ry,
               "recv_x": x + c * dx - s * dy if has else np.nan, "recv_y": y + s * dx + c * dy if has else np.nan,
               "err": float(info["tracking_error"])}
        if obs.shape[-1] > i["packet_age"]:
            row["packet_age"] = float(obs[i["packet_age"]])
        f = np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1, 1) * limits
        row.update({"F_u": f[0], "F_v": f[1], "F_r": f[2]})
        if hasattr(policy, "reference"):
            own = np.asarray(policy.reference(obs)).reshape(-1)[:3]
            ox, oy = x + c * own[0] - s * own[1], y + s * own[0] + c * own[1]
            # estimated target = own reference minus the offset p_d rotated by the estimated heading
            opsi = psi + own[2] - spec.psi_d
            px, py = spec.p_d
            row.update({"own_ref_x": ox, "own_ref_y": oy,
                        "est_x": ox - (np.cos(opsi) * px - np.sin(opsi) * py),
                        "est_y": oy - (np.sin(opsi) * px + np.cos(opsi) * py)})
        ex, ey = rx - x, ry - y
        row["along_track"] = -(ex * np.cos(tpsi) + ey * np.sin(tpsi))  # > 0: follower ahead of the reference
        row["cross_track"] = -(-ex * np.sin(tpsi) + ey * np.cos(tpsi))  # > 0: follower to port of it
        rows.append(row)
        if term or trunc:
            break
    env.close()
    df = pd.DataFrame(rows)
    df.attrs["force_limits"] = tuple(float(v) for v in limits)
    return df


def binned_breakdown(episodes: pd.DataFrame, condition: str, metric: str = "true_steady_mean",
                     bins: int = 6) -> pd.DataFrame:
    """IQM of ``metric`` per policy in equal-width bins of a drawn condition (pooled over the
    tiers in ``episodes``): columns policy, bin_center, iqm, episodes."""
    from agents.benchmark import iqm

    if condition not in episodes:
        raise ValueError(f"condition={condition!r} is not a column: valid conditions are "
                         f"{[c for c in episodes.columns if c.startswith('cond_')]}")
    ep = episodes.assign(_score=scores(episodes, metric))
    v = ep[condition].astype(float)
    lo, hi = float(v.min()), float(v.max())
    edges = np.linspace(lo, hi if hi > lo else lo + 1e-9, bins + 1)
    ep["_bin"] = np.clip(np.digitize(v, edges[1:-1]), 0, bins - 1)
    out = []
    for (pol, b), d in ep.groupby(["policy", "_bin"], sort=False):
        out.append({"policy": pol, "bin_center": 0.5 * (edges[b] + edges[b + 1]), "iqm": float(iqm(d["_score"])),
                    "episodes": len(d)})
    return pd.DataFrame(out).sort_values(["policy", "bin_center"]).reset_index(drop=True)


# --- figures -----------------------------------------------------------------------------

def _fig_leaderboard(board: pd.DataFrame):
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    tiers = list(dict.fromkeys(board["tier"]))
    m = "true_steady_mean"
    fig = make_subplots(rows=1, cols=len(tiers), subplot_titles=[_txt(t) for t in tiers], horizontal_spacing=0.08)
    for k, tier in enumerate(tiers, start=1):
        sub = board[board["tier"] == tier].sort_values(f"{m}_iqm", ascending=False)
        fig.add_trace(go.Bar(
            x=sub[f"{m}_iqm"], y=[_txt(p) for p in sub["policy"]], orientation="h", showlegend=False,
            marker_color=["#ff7f0e" if kd == "classical" else "#999999" if kd == "reference" else "#1f77b4"
                          for kd in sub["kind"]],
            error_x={"type": "data", "symmetric": False, "array": sub[f"{m}_iqm_hi"] - sub[f"{m}_iqm"],
                     "arrayminus": sub[f"{m}_iqm"] - sub[f"{m}_iqm_lo"]},
            hovertemplate="%{y}: %{x:.4f} m<extra></extra>"), row=1, col=k)
        fig.update_xaxes(type="log", title_text="IQM steady error [m]", row=1, col=k)
    fig.update_layout(height=120 + 28 * board.groupby("tier").size().max(), margin={"l": 10, "r": 10, "t": 40},
                      title="Steady-state true-reference error: IQM and 95 % CI (orange classical, blue learned"
                            + (", grey floors)" if (board["kind"] == "reference").any() else ")"))
    return fig


def _fig_breakdown(episodes: pd.DataFrame, condition: str, label: str):
    """One panel per tier: the condition is binned within the tier (pooling tiers would plot
    the tier, not the condition)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    tiers = [str(t) for t in dict.fromkeys(episodes["tier"])] if "tier" in episodes else [""]
    fig = make_subplots(rows=1, cols=len(tiers), subplot_titles=[_txt(t) for t in tiers], horizontal_spacing=0.06)
    shown: set[str] = set()
    for c, tier in enumerate(tiers, start=1):
        ep = episodes[episodes["tier"].astype(str) == tier] if tier else episodes
        if condition not in ep or ep[condition].nunique() == 0:
            continue
        bd = binned_breakdown(ep, condition)
        for pol, d in bd.groupby("policy", sort=False):
            fig.add_trace(go.Scatter(x=d["bin_center"], y=d["iqm"], mode="lines+markers", name=_txt(pol),
                                     legendgroup=str(pol), showlegend=str(pol) not in shown,
                                     line={"color": _color(pol)}, customdata=d["episodes"],
                                     hovertemplate="%{x:.3g}: %{y:.4f} m (%{customdata} episodes)<extra></extra>"),
                          row=1, col=c)
            shown.add(str(pol))
        fig.update_xaxes(title_text=_txt(label), row=1, col=c)
        fig.update_yaxes(type="log", row=1, col=c)
    fig.update_yaxes(title_text="IQM steady error [m]", row=1, col=1)
    fig.update_layout(title=f"Steady-state error vs {_txt(label)} (6 equal-width bins within each tier, IQM per bin)",
                      height=400)
    return fig


def _fig_forces(runs: dict[str, pd.DataFrame]):
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    names = [("F_u", "N"), ("F_v", "N"), ("F_r", "N m")]
    fig = make_subplots(rows=3, cols=1, shared_xaxes=True, subplot_titles=[n for n, _ in names])
    limits = next(iter(runs.values())).attrs.get("force_limits", (np.nan,) * 3)
    for k, (pol, df) in enumerate(runs.items()):
        for j, (n, _) in enumerate(names, start=1):
            fig.add_trace(go.Scatter(x=df["time"], y=df[n], name=_txt(pol), legendgroup=str(k), showlegend=j == 1,
                                     line={"color": _color(pol), "width": 1}), row=j, col=1)
    for j, ((n, unit), lim) in enumerate(zip(names, limits, strict=True), start=1):
        for sgn in (1, -1):
            fig.add_hline(y=sgn * lim, line_dash="dash", line_color="black", row=j, col=1)
        fig.update_yaxes(title_text=f"{n} [{unit}]", row=j, col=1)
    fig.update_xaxes(title_text="time [s]", row=3, col=1)
    fig.update_layout(title="Forces over time (dashed: force limits)", height=620)
    return fig


def _fig_track(runs: dict[str, pd.DataFrame]):
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, subplot_titles=["along-track", "cross-track"])
    for k, (pol, df) in enumerate(runs.items()):
        for j, col in enumerate(("along_track", "cross_track"), start=1):
            fig.add_trace(go.Scatter(x=df["time"], y=df[col], name=_txt(pol), legendgroup=str(k), showlegend=j == 1,
                                     line={"color": _color(pol), "width": 1}), row=j, col=1)
    fig.update_yaxes(title_text="along [m] (+: ahead)", row=1, col=1)
    fig.update_yaxes(title_text="cross [m] (+: to port)", row=2, col=1)
    fig.update_xaxes(title_text="time [s]", row=2, col=1)
    fig.update_layout(title="Error from the true reference in the target's heading frame", height=520)
    return fig


def _fig_targets(df: pd.DataFrame, title: str):
    import plotly.graph_objects as go

    fig = go.Figure()
    fig.add_trace(go.Scatter(x=df["target_x"], y=df["target_y"], mode="lines", name="true target",
                             line={"color": "black"}))
    fig.add_trace(go.Scatter(x=df["recv_x"], y=df["recv_y"], mode="markers", name="received (delayed) target",
                             marker={"size": 3, "color": "#d62728"}))
    if "est_x" in df:
        fig.add_trace(go.Scatter(x=df["est_x"], y=df["est_y"], mode="lines", name="estimated target",
                                 line={"color": "#2ca02c", "dash": "dot"}))
    fig.add_trace(go.Scatter(x=df["follower_x"], y=df["follower_y"], mode="lines", name="follower",
                             line={"color": "#1f77b4", "width": 1}))
    fig.update_layout(title=_txt(title), xaxis_title="x [m]", yaxis_title="y [m]", height=520,
                      yaxis={"scaleanchor": "x", "scaleratio": 1})
    return fig


def _fig_replay(df: pd.DataFrame, title: str, every: int = 10, trail_s: float = 20.0):
    import plotly.graph_objects as go

    idx = list(range(0, len(df), every)) + ([len(df) - 1] if (len(df) - 1) % every else [])
    dt = float(df["time"].iloc[1] - df["time"].iloc[0]) if len(df) > 1 else 1.0
    trail = max(1, int(round(trail_s / dt)))

    def moving(k: int) -> list:
        d = df.iloc[max(0, k - trail): k + 1]
        last = df.iloc[k]
        return [go.Scatter(x=d["recv_x"], y=d["recv_y"], mode="markers", marker={"size": 3, "color": "#d62728"},
                           name=f"received target (last {trail_s:g} s)"),
                go.Scatter(x=[last["target_x"], last["follower_x"], last["recv_x"]],
                           y=[last["target_y"], last["follower_y"], last["recv_y"]], mode="markers",
                           marker={"size": [12, 12, 10], "color": ["black", "#1f77b4", "#d62728"],
                                   "symbol": ["triangle-up", "circle", "x"]},
                           name="now: true target / follower / received")]

    static = [go.Scatter(x=df["target_x"], y=df["target_y"], mode="lines", line={"color": "#bbbbbb"},
                         name="true target path"),
              go.Scatter(x=df["follower_x"], y=df["follower_y"], mode="lines", line={"color": "#9ecae1"},
                         name="follower path")]
    frames = [go.Frame(data=moving(k), traces=[2, 3], name=f"{df['time'].iloc[k]:.1f}") for k in idx]
    fig = go.Figure(data=static + moving(idx[0]), frames=frames)
    steps = [{"args": [[f.name], {"frame": {"duration": 0, "redraw": True}, "mode": "immediate"}],
              "label": f.name, "method": "animate"} for f in frames]
    fig.update_layout(
        title=_txt(title), height=620, xaxis={"title": "x [m]"},
        yaxis={"title": "y [m]", "scaleanchor": "x", "scaleratio": 1},
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

def _table_html(board: pd.DataFrame) -> str:
    m0 = LEADERBOARD_METRICS[0]
    parts = []
    for tier, sub in board.groupby("tier", sort=False):
        best = sub["best_classical"].iloc[0]
        parts.append(f"<h3>{html.escape(str(tier))}" + (f" (best classical: {html.escape(str(best))})" if
                                                        isinstance(best, str) else "") + "</h3>")
        head = ["policy", "kind", "runs x episodes", "steady IQM [m] [95 % CI]", "steady mean [m] [95 % CI]",
                "full IQM [m] [95 % CI]", "full mean [m] [95 % CI]", "IQM vs best classical [%]",
                "paired diff vs best classical [m] [95 % CI]", "P(better) [95 % CI]", "terminated [%]"]
        gap = "gap_closed" in sub and sub["gap_closed"].notna().any()  # floors present (agents/floors.py)
        head += ["gap closed [-]"] if gap else []
        parts.append("<table class='leaderboard' data-tier='" + html.escape(str(tier)) + "'><thead><tr>" +
                     "".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>")
        for _, r in sub.sort_values(f"{m0}_iqm").iterrows():
            def ci(m: str, stat: str, row: pd.Series = r) -> str:
                return f"{row[f'{m}_{stat}']:.4f} [{row[f'{m}_{stat}_lo']:.4f}, {row[f'{m}_{stat}_hi']:.4f}]"

            chg = r.get(f"{m0}_iqm_change_pct")
            cells = [r["policy"], r["kind"], f"{r['runs']} x {r['episodes'] // max(int(r['runs']), 1)}",
                     ci("true_steady_mean", "iqm"), ci("true_steady_mean", "mean"), ci("true_full_mean", "iqm"),
                     ci("true_full_mean", "mean"),
                     "-" if chg is None or not np.isfinite(chg) else f"{chg:+.1f} %",
                     "-" if r["policy"] == best or not np.isfinite(r.get("paired_diff", np.nan)) else
                     f"{r['paired_diff']:+.4f} [{r['paired_diff_lo']:+.4f}, {r['paired_diff_hi']:+.4f}]",
                     "-" if not np.isfinite(r["poi"]) else f"{r['poi']:.2f} [{r['poi_lo']:.2f}, {r['poi_hi']:.2f}]",
                     f"{100 * r['termination_rate']:.0f} %"]
            if gap:
                cells.append("-" if not np.isfinite(r["gap_closed"]) else f"{r['gap_closed']:.2f}")
            cls = "leaderboard-row best" if r["policy"] == best else "leaderboard-row"
            cls += " reference" if r["kind"] == "reference" else ""
            parts.append(f"<tr class='{cls}' data-policy='{html.escape(str(r['policy']), quote=True)}'>" +
                         "".join(f"<td>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
        parts.append("</tbody></table>")
    return "\n".join(parts)


_CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1400px}
table{border-collapse:collapse;margin-bottom:1em;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px}
tr.best{font-weight:bold;background:#fff4e5}tr.reference{color:#666;font-style:italic}th{background:#f3f3f3}pre{background:#f7f7f7;padding:1em;
overflow:auto;font-size:11px}.note{color:#555;font-size:13px}"""


_OPTIONAL_TRACE_COLUMNS = ("own_ref_x", "own_ref_y", "est_x", "est_y", "packet_age")


def _stored_episode(traces: pd.DataFrame | None, tier: str, label: str, seed: int) -> pd.DataFrame | None:
    """The recorded per-step episode of ``label`` on ``tier`` / ``seed`` from ``traces.parquet``."""
    if traces is None or traces.empty or not {"tier", "policy", "seed"} <= set(traces.columns):
        return None
    d = traces[(traces["tier"].astype(str) == tier) & (traces["policy"].astype(str) == label)
               & (traces["seed"] == seed)]
    if d.empty:
        return None
    d = d.drop(columns=["tier", "policy", "seed"]).reset_index(drop=True)
    empty = [c for c in _OPTIONAL_TRACE_COLUMNS if c in d and d[c].isna().all()]
    return d.drop(columns=empty)


def write_report(bench_dir: str | Path = "results/benchmark", out: str | Path | None = None, *,
                 replay_policy: str | None = None, replay_tier: str | None = None, replay_seed: int | None = None,
                 time_policies: Sequence[str] | None = None) -> Path:
    """Write the HTML report of a benchmark directory and return its path.

    Built from the stored tables alone (see the module docstring): never loads a model file.

    Args:
        bench_dir: a directory written by :func:`agents.benchmark.benchmark`.
        out: HTML file (default ``<bench_dir>/report.html``).
        replay_policy: policy label of the replay (default: the best policy on the replay tier
            with a recorded episode).
        replay_tier: tier of the time plots and the replay (default: Hard if benchmarked,
            else the last tier).
        replay_seed: test seed of the replay (default: the seed of the recorded episodes, else
            the tier's first benchmarked seed).
        time_policies: policies of the force / track plots (default: the best classical, the
            best learned and PROPOSED where present and recorded).

    Raises:
        FileNotFoundError: no benchmark in ``bench_dir``.
        ValueError: unknown policy, tier or seed (names the valid ones); a learned policy asked
            for without a recorded episode; files that are corrupt or from different runs.
    """
    import plotly.offline

    from controllers import make_controller

    res = load_result(bench_dir)
    board, episodes, prov, traces = res.leaderboard, res.episodes, res.provenance, res.traces
    _PALETTE.clear()
    for p in dict.fromkeys(board["policy"].astype(str)):
        _color(p)
    tiers = [str(t) for t in dict.fromkeys(board["tier"])]
    if not tiers:
        raise ValueError(f"{Path(bench_dir) / 'leaderboard.csv'} has no rows")
    tier = replay_tier if replay_tier is not None else ("Hard" if "Hard" in tiers else tiers[-1])
    if tier not in tiers:
        raise ValueError(f"replay_tier={replay_tier!r} was not benchmarked: valid tiers are {tiers}")
    _, env_id = resolve_tier(tier)
    sub = board[(board["tier"].astype(str) == tier) & (board["kind"].astype(str) != "reference")]
    sub = sub.sort_values("true_steady_mean_iqm")  # (floors are references: nothing to replay)
    labels = [str(p) for p in sub["policy"]]
    kinds = dict(zip(labels, sub["kind"].astype(str), strict=True))
    seeds = sorted(int(x) for x in episodes.loc[episodes["tier"].astype(str) == tier, "seed"].unique())
    if not seeds:
        raise ValueError(f"{Path(bench_dir) / 'episodes.parquet'} has no episodes of tier {tier!r}")
    traced = sorted(int(x) for x in traces.loc[traces["tier"].astype(str) == tier, "seed"].unique()) \
        if traces is not None and not traces.empty else []
    seed = int(replay_seed) if replay_seed is not None else (traced[0] if traced else seeds[0])
    if seed not in seeds:
        raise ValueError(f"replay_seed={replay_seed!r} was not benchmarked on {tier}: valid seeds are "
                         f"{seeds[0]}..{seeds[-1]} ({len(seeds)} seeds)")
    probe = gym.make(env_id)
    task_spec = probe.unwrapped.task_spec
    probe.close()
    limits = tuple(float(v) for v in task_spec.force_limits)
    controllers_by_label = {str(p.get("label")): p.get("controller") for p in prov["config"].get("policies", [])
                            if isinstance(p, dict)}
    scripted = set(_controllers())
    cache: dict[str, pd.DataFrame | None] = {}

    def episode(label: str) -> pd.DataFrame | None:
        """Recorded episode, or a scripted controller of this package re-run; never a model file."""
        if label not in cache:
            df = _stored_episode(traces, tier, label, seed)
            ctrl = controllers_by_label.get(label)
            if df is None and kinds.get(label) == "classical" and ctrl in scripted:
                df = rollout_episode(make_controller(ctrl, task_spec), env_id, seed)
            if df is not None:
                df.attrs["force_limits"] = limits
            cache[label] = df
        return cache[label]

    def refuse(arg: str, label: str) -> None:
        have = [p for p in labels if episode(p) is not None]
        raise ValueError(f"{arg}={label!r} has no recorded episode on {tier}, seed {seed} in "
                         f"{Path(bench_dir) / 'traces.parquet'} (a report never loads model files): policies with "
                         f"one are {have}")

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
    est_label = next((p for p in runs if "est_x" in runs[p]), policy)
    figs = [
        ("Leaderboard", _fig_leaderboard(board)),
        ("Error vs latency", _fig_breakdown(episodes, "cond_latency_s", "latency [s]")),
        ("Error vs loss rate", _fig_breakdown(episodes, "cond_loss_prob", "packet loss probability")),
    ]
    if time_policies:
        figs += [("Forces", _fig_forces({p: runs[p] for p in time_policies})),
                 ("Along- and cross-track error", _fig_track({p: runs[p] for p in time_policies}))]
    if policy is not None:
        figs += [("Delayed, estimated and true target",
                  _fig_targets(runs[est_label], f"{tier}, seed {seed}: delayed (received), estimated ({est_label}) "
                                                f"and true target")),
                 ("Episode replay", _fig_replay(runs[policy], f"Replay: {policy} on {tier}, seed {seed}"))]
    note = ("" if not missing else
            f" Learned policies without a recorded episode in traces.parquet (left out of the time plots and the "
            f"replay; a report never loads model files): {html.escape(', '.join(missing))}.")
    body = [f"<h1>auv-follow benchmark</h1><p class='note'>Tiers: {html.escape(', '.join(tiers))}. "
            f"Time plots and replay: {html.escape(tier)} ({html.escape(env_id)}), test seed {seed}. Every number is "
            f"reproduced by the command in the provenance below.{note}</p>",
            "<h2>Leaderboard</h2>", _table_html(board)]
    for k, (title, fig) in enumerate(figs):
        body.append(f"<h2>{html.escape(title)}</h2>")
        body.append(fig.to_html(full_html=False, include_plotlyjs=False, div_id=f"fig{k}",
                                config={"displaylogo": False, "responsive": True}))
    body.append("<h2>Provenance</h2><details><summary>configuration, versions and the command (click to "
                "expand)</summary><pre>" + html.escape(json.dumps(prov, indent=1, default=str)) + "</pre></details>")
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>auv-follow benchmark</title>"
            "<link rel='icon' href='data:,'>"
            f"<style>{_CSS}</style><script type='text/javascript'>{plotly.offline.get_plotlyjs()}</script>"
            "</head><body>" + "\n".join(body) + "</body></html>")
    path = Path(out) if out is not None else Path(bench_dir) / "report.html"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        tmp.write_text(page, encoding="utf-8")
        tmp.replace(path)  # an interrupted write never leaves half a page
    finally:
        tmp.unlink(missing_ok=True)
    return path
