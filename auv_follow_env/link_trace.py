"""Recorded link traces: replay a modem's log in place of the v1 link model, and record one.

A **link trace** is a table with one row per packet sent from t = 0 on, in send order
(``docs/link_traces.md`` gives the format, how to convert a modem or USBL log, and an example):

| column | unit | required | meaning |
|---|---|---|---|
| ``send_time`` | s | yes | when the target's state was measured and sent (t = 0: the episode's start) |
| ``arrival_time`` | s | yes | when the packet reached the follower; empty (NaN) if it was lost |
| ``lost`` | 0/1 | no | 1: lost (then ``arrival_time`` must be empty); default: lost iff no arrival time |
| ``noise_x``, ``noise_y`` | m | no | the fix's position error (measured minus true), default 0 |
| ``noise_psi`` | rad | no | the fix's heading error, default 0 |
| ``noise_u``, ``noise_v`` | m/s | no | the fix's velocity error (target body frame), default 0 |
| ``noise_r`` | rad/s | no | the fix's yaw-rate error, default 0 |

``gym.make(v1_id, link_trace=FILE)`` replays it: the physics, the target, the current and the
env's own link model run exactly as without the trace (same seed, same draws), but the follower
hears the trace's packets instead of the model's. A packet of the trace measures the *simulated*
target at its send time, adds its recorded error and is usable from its arrival time on, with
the env's rules: times fall on the control grid (a packet is sent on the first step at or after
its ``send_time`` and usable from the first step at or after its ``arrival_time``), the newest
arrived packet replaces the held one and older packets still in flight are discarded. The
warm-up before t = 0 (``warmup_s``) is the env's own link: the packet held at t = 0 and those in
flight then come from the model. After the trace's last packet nothing more arrives.

:func:`record_link_trace` writes the trace of a simulated episode (``auv-follow trace``); replaying
it under the same seed and the same policy gives the same episode.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from auv_follow_env import dynamics as dyn
from auv_follow_env._files import check_size

__all__ = ["LinkTrace", "TraceLink", "read_link_trace", "record_link_trace", "TRACE_COLUMNS", "NOISE_COLUMNS"]

NOISE_COLUMNS = ("noise_x", "noise_y", "noise_psi", "noise_u", "noise_v", "noise_r")
TRACE_COLUMNS = ("send_time", "arrival_time", "lost") + NOISE_COLUMNS
#: the largest trace accepted (packets); a day at 10 Hz is 864,000
MAX_PACKETS = 10_000_000
_SUFFIXES = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet"}
_EPS = 1e-6  # (as the kernel: a time within 1e-6 steps of a grid point is on it)


@dataclass(frozen=True, eq=False)
class LinkTrace:
    """A validated link trace: per packet its send time [s], arrival time [s] (NaN: lost) and
    the fix's error (n, 6) in the order of :data:`NOISE_COLUMNS`. ``source`` names where it came
    from (for messages)."""

    send_time: np.ndarray
    arrival_time: np.ndarray
    noise: np.ndarray
    source: str = "<trace>"

    def __len__(self) -> int:
        return int(self.send_time.shape[0])

    @property
    def lost(self) -> np.ndarray:
        return np.isnan(self.arrival_time)

    def to_frame(self) -> pd.DataFrame:
        """The trace as a table with every column of :data:`TRACE_COLUMNS`."""
        df = pd.DataFrame({"send_time": self.send_time, "arrival_time": self.arrival_time,
                           "lost": self.lost.astype(np.int64)})
        for j, name in enumerate(NOISE_COLUMNS):
            df[name] = self.noise[:, j]
        return df

    def write(self, path: str | os.PathLike) -> Path:
        """Write the trace as CSV (``.csv``; every float reads back bit for bit) or Parquet
        (``.parquet``/``.pq``), atomically (a temporary file renamed into place)."""
        out = Path(path)
        kind = _kind(out, "path")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        df = self.to_frame()
        if kind == "csv":
            df.to_csv(tmp, index=False)  # (pandas writes the shortest repr that reads back exactly)
        else:
            df.to_parquet(tmp, index=False)
        os.replace(tmp, out)
        return out

    def steps(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Send and arrival steps on the control grid of step ``dt`` (arrival -1: lost)."""
        send = np.ceil(self.send_time / dt - _EPS).astype(np.int64)
        arr = np.where(self.lost, -1.0, np.ceil(np.nan_to_num(self.arrival_time) / dt - _EPS)).astype(np.int64)
        return send, arr


def _kind(path: Path, name: str) -> str:
    kind = _SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"{name}={str(path)!r} has an unknown suffix: a link trace is a .csv or .parquet "
                         f"(.pq) file")
    return kind


def _where(source: str, i: int, csv: bool) -> str:
    return f"{source}: packet {i} (CSV line {i + 2})" if csv else f"{source}: packet {i} (row {i})"


def _column(df: pd.DataFrame, name: str, source: str, csv: bool) -> np.ndarray:
    col = df[name]
    try:
        values = pd.to_numeric(col, errors="raise").to_numpy(dtype=np.float64)
    except (TypeError, ValueError):
        bad = next(i for i, v in enumerate(col) if _not_number(v))
        raise ValueError(f"{_where(source, bad, csv)}: {name}={col.tolist()[bad]!r} is not a number") from None
    return values


def _not_number(v: object) -> bool:
    try:
        float(v)
    except (TypeError, ValueError):
        return True
    return False


def read_link_trace(trace: Any, *, name: str = "link_trace") -> LinkTrace:
    """A :class:`LinkTrace` from a CSV or Parquet file, a pandas DataFrame or a LinkTrace.

    Raises:
        ValueError: for a missing or unreadable file, an unknown or missing column, a value that
            is not a number, a send time that is negative, not finite or not after the previous
            packet's (on the control grid that check is the env's), an arrival before its send
            time, or a ``lost`` mark that contradicts ``arrival_time``; the message names the packet
            and its CSV line.
        TypeError: if ``trace`` is none of those types.
    """
    if isinstance(trace, LinkTrace):
        return trace
    csv = False
    if isinstance(trace, pd.DataFrame):
        df, source = trace, "<DataFrame>"
    elif isinstance(trace, (str, os.PathLike)):
        path = Path(trace)
        kind = _kind(path, name)
        if not path.is_file():
            raise ValueError(f"{name}={str(path)!r}: no such file")
        check_size(path, "parquet" if kind == "parquet" else "table")
        source, csv = str(path), kind == "csv"
        try:
            df = pd.read_csv(path) if csv else pd.read_parquet(path)
        except Exception as exc:  # (pandas and pyarrow raise many types for a malformed file)
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"{name}={str(path)!r} could not be read as {kind}: {first}") from None
    else:
        raise TypeError(f"{name}={trace!r} is a {type(trace).__name__}: pass a path to a .csv or .parquet "
                        f"file, a pandas DataFrame or a LinkTrace")
    df.columns = [str(c).strip() for c in df.columns]
    unknown = [c for c in df.columns if c not in TRACE_COLUMNS]
    if unknown:
        raise ValueError(f"{source}: unknown column(s) {unknown}: a link trace has the columns "
                         f"{list(TRACE_COLUMNS)} (send_time and arrival_time required); drop or rename the others")
    missing = [c for c in ("send_time", "arrival_time") if c not in df.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing}: a link trace needs send_time and arrival_time "
                         f"[s] per packet (arrival_time empty for a lost packet)")
    n = len(df)
    if n == 0:
        raise ValueError(f"{source}: the trace has no packets")
    if n > MAX_PACKETS:
        raise ValueError(f"{source}: {n} packets: at most {MAX_PACKETS:,} are accepted")
    send = _column(df, "send_time", source, csv)
    arrival = _column(df, "arrival_time", source, csv)
    bad = np.flatnonzero(~np.isfinite(send) | (send < 0.0))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{_where(source, i, csv)}: send_time={float(send[i])!r} is invalid: a finite time >= 0 s "
                         f"(the warm-up before t = 0 is the env's own link)")
    back = np.flatnonzero(np.diff(send) <= 0.0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(f"{_where(source, i, csv)}: send_time={float(send[i])!r} is not after the previous packet's "
                         f"({float(send[i - 1])!r}): packets must be in send order, one per send time")
    bad = np.flatnonzero(np.isinf(arrival) | (arrival < send))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{_where(source, i, csv)}: arrival_time={float(arrival[i])!r} is invalid: a time >= its "
                         f"send_time ({float(send[i])!r}), or empty if the packet was lost")
    if "lost" in df.columns:
        lost = _column(df, "lost", source, csv)
        bad = np.flatnonzero(~np.isin(lost, (0.0, 1.0)))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{_where(source, i, csv)}: lost={df['lost'].tolist()[i]!r} is invalid: 0 or 1")
        bad = np.flatnonzero((lost == 1.0) != np.isnan(arrival))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{_where(source, i, csv)}: lost={int(lost[i])} contradicts arrival_time="
                             f"{float(arrival[i])!r}: a lost packet has no arrival time, an arrived one has one")
    noise = np.zeros((n, len(NOISE_COLUMNS)))
    for j, col in enumerate(NOISE_COLUMNS):
        if col in df.columns:
            noise[:, j] = _column(df, col, source, csv)
            bad = np.flatnonzero(~np.isfinite(noise[:, j]))
            if bad.size:
                i = int(bad[0])
                raise ValueError(f"{_where(source, i, csv)}: {col}={float(noise[i, j])!r} is invalid: a finite error "
                                 f"(0 for an exact fix)")
    return LinkTrace(send, arrival, noise, source)


class TraceLink:
    """The replay of a :class:`LinkTrace` in one env (used by :class:`~auv_follow_env.env.AUVFollowEnv`):
    its own held packet, packets in flight and counters, next to the kernel's link, which keeps
    running so that the episode's draws are those of the env without a trace."""

    def __init__(self, trace: LinkTrace, dt: float, n_steps: int) -> None:
        self.trace = trace
        self.dt = float(dt)
        self._send, self._arr = trace.steps(self.dt)
        if len(self._send) > 1 and np.any(np.diff(self._send) <= 0):
            i = int(np.flatnonzero(np.diff(self._send) <= 0)[0]) + 1
            t1, t0 = float(trace.send_time[i]), float(trace.send_time[i - 1])
            raise ValueError(f"{trace.source}: packet {i} is sent at {t1!r} s, on the same control step as packet "
                             f"{i - 1} ({t0!r} s) with dt={self.dt:g} s: at most one packet per step")
        self.n_steps = n_steps
        self.reset_state()

    def reset_state(self) -> None:
        self._next = 0  # the next trace packet to send
        self._flight: list[tuple[int, int, np.ndarray]] = []  # (measured at, arrives at, x y psi u v r)
        self.has = False
        self.new = False
        self.meas = 0
        self.arr = 0
        self.x = np.zeros(6)
        self.stats = {"sent": 0, "lost": 0, "arrived": 0, "discarded": 0, "overflow": 0}

    def reset(self, sim: Any, truth_target: np.ndarray) -> None:
        """Start an episode: the warm-up's packets (measured before t = 0) from the kernel's link in
        env 0 of ``sim``, then the trace's packets sent at step 0 (``truth_target``: the target's
        x, y, psi, u, v, r at t = 0)."""
        self.reset_state()
        p = sim.proc[0]
        q = sim.queue[0]
        qlen, head = int(p[dyn.R_QLEN]), int(p[dyn.R_QHEAD])
        for m in range(qlen):
            e = q[(head + m) % q.shape[0]]
            if e[dyn.Q_MEAS] < 0:
                self._flight.append((int(e[dyn.Q_MEAS]), int(e[dyn.Q_ARR]), e[dyn.Q_X:dyn.Q_X + 6].copy()))
        if p[dyn.R_HAS] != 0.0 and p[dyn.R_HMEAS] < 0:
            self.has, self.meas, self.arr = True, int(p[dyn.R_HMEAS]), int(p[dyn.R_HARR])
            self.x = p[dyn.R_HX:dyn.R_HX + 6].copy()
            self.new = p[dyn.R_NEW] != 0.0 and self.arr == 0
        self._tick(0, truth_target, keep_new=True)

    def step(self, k: int, truth_target: np.ndarray) -> None:
        """Control step ``k``: send the trace's packets of this step, then take the newest arrived."""
        self._tick(k, truth_target, keep_new=False)

    def _tick(self, k: int, truth: np.ndarray, keep_new: bool) -> None:
        if not keep_new:
            self.new = False
        while self._next < len(self._send) and self._send[self._next] <= k:
            j = self._next
            self._next += 1
            self.stats["sent"] += 1
            if self._arr[j] < 0:
                self.stats["lost"] += 1
                continue
            self._flight.append((k, int(self._arr[j]), truth + self.trace.noise[j]))
        newest = -1
        for m, (_, a, _) in enumerate(self._flight):
            if a <= k:
                newest = m
        if newest < 0:
            return
        meas, _, x = self._flight[newest]
        if meas >= 0:
            self.stats["arrived"] += 1
        self.stats["discarded"] += sum(1 for e in self._flight[:newest] if e[0] >= 0)
        del self._flight[:newest + 1]
        self.has, self.new, self.meas, self.arr, self.x = True, True, meas, k, x

    def observe(self, obs: np.ndarray, sim: Any, k: int, fast: bool) -> np.ndarray:
        """Overwrite the packet fields (5-13, 16-19) of the v1 observation ``obs`` with the held
        packet of the trace (the env's formulas: :func:`auv_follow_env.dynamics._observe_dp`)."""
        if not self.has:
            obs[5:14] = 0.0
            obs[16:20] = (0.0, 0.0, 1.0 if self.new else 0.0, 0.0)
            return obs
        p = sim.proc[0]
        st = sim.state[0]
        x, y, ps = st[0], st[1], st[2]
        c, s = p[dyn.R_PSC], p[dyn.R_PSS]
        cfg = sim.cfg
        pdx, pdy = cfg[dyn.C_PDX], cfg[dyn.C_PDY]
        xd, yd, psd = self.x[0], self.x[1], self.x[2]
        cd, sd = math.cos(psd), math.sin(psd)
        dpsi = psd - ps
        if fast and abs(dpsi) <= dyn.FAST_TRIG_MAX:
            sdp, cdp = _fast_sincos()(dpsi)
        else:
            cdp, sdp = math.cos(dpsi), math.sin(dpsi)
        ex, ey = xd - x, yd - y
        rx = xd + cd * pdx - sd * pdy - x
        ry = yd + sd * pdx + cd * pdy - y
        obs[5] = c * ex + s * ey
        obs[6] = -s * ex + c * ey
        obs[7] = cdp
        obs[8] = sdp
        obs[9:12] = self.x[3:6]
        obs[12] = c * rx + s * ry
        obs[13] = -s * rx + c * ry
        obs[16] = (k - self.meas) * self.dt
        obs[17] = (k - self.arr) * self.dt
        obs[18] = 1.0 if self.new else 0.0
        obs[19] = 1.0
        return obs


_FAST: list = []


def _fast_sincos() -> Callable[[float], tuple[float, float]]:
    """dynamics.fast_sincos callable from Python (compiled once, on the first replayed step)."""
    if not _FAST:
        from numba import njit

        _FAST.append(njit(cache=True)(dyn.fast_sincos.py_func))
    return _FAST[0]


def record_link_trace(env: Any, policy: Any, seed: int, *, progress: Callable[[], None] | None = None) -> LinkTrace:
    """Run one episode of the v1 env ``env`` (a single env made by ``gym.make``) under ``policy``
    (anything with ``predict(obs)`` returning an action, or a callable obs -> action; ``reset()``
    is called if it has one) and return its link trace: every packet sent from t = 0 on, with its
    send and arrival times and its fix error (the measured minus the true target state at the send
    time). The position errors of a range-dependent fix noise depend on the follower's path, hence
    on the policy; the send times, latencies and losses do not.

    Raises:
        ValueError: if ``env`` is not a v1 env or replays a trace itself.
    """
    base = env.unwrapped
    sim = getattr(base, "_sim", None)
    if sim is None or not sim.v1:
        raise ValueError(f"env={env!r} is not a v1 env: link traces exist on the AUVFollow-*-v1 ids only")
    if getattr(base, "_trace_link", None) is not None:
        raise ValueError("env already replays a link trace: record from the env without link_trace")
    dt = base.config.dt
    obs, info = env.reset(seed=int(seed))
    if hasattr(policy, "reset"):
        policy.reset()
    act = policy.predict if hasattr(policy, "predict") else policy
    rows: list[tuple[float, float, np.ndarray]] = []

    def collect(k: int, truth: np.ndarray) -> None:
        p = sim.proc[0]
        if int(p[dyn.R_SENT]) == len(rows):
            return  # nothing sent this step
        q = sim.queue[0]
        qlen, head = int(p[dyn.R_QLEN]), int(p[dyn.R_QHEAD])
        entry = None
        for m in range(qlen):
            e = q[(head + m) % q.shape[0]]
            if int(e[dyn.Q_MEAS]) == k:
                entry = (e[dyn.Q_ARR], e[dyn.Q_X:dyn.Q_X + 6])
        if entry is None and p[dyn.R_HAS] != 0.0 and int(p[dyn.R_HMEAS]) == k:
            entry = (p[dyn.R_HARR], p[dyn.R_HX:dyn.R_HX + 6])  # arrived on the step it was sent
        if entry is None:
            rows.append((k * dt, math.nan, np.zeros(6)))
        else:
            rows.append((k * dt, float(entry[0]) * dt, np.asarray(entry[1], dtype=np.float64) - truth))

    collect(0, np.asarray(info["true_target"], dtype=np.float64))
    done = False
    while not done:
        out = act(obs)
        action = out[0] if isinstance(out, tuple) else out
        obs, _, term, trunc, info = env.step(action)
        collect(int(sim.k[0]), np.asarray(info["true_target"], dtype=np.float64))
        done = term or trunc
        if progress is not None:
            progress()
    if not rows:
        raise ValueError("the episode sent no packet from t = 0 on: there is no trace to record")
    # times to the nanosecond (38 * 0.05 is 1.9000000000000001 s): the steps they fall on are the same
    send = np.round(np.array([r[0] for r in rows]), 9)
    arrival = np.round(np.array([r[1] for r in rows]), 9)
    noise = np.array([r[2] for r in rows])
    return LinkTrace(send, arrival, noise, f"<recorded: {env.spec.id if env.spec else 'env'} seed {seed}>")
