"""``auv-follow benchmark --address``: the benchmark's cells on a Ray cluster give the local run's tables.

A Ray head is started on this machine (``ray start --head``) and the benchmark connects to it as
to any cluster; the expected tables are those of the same command without ``--address``."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[sweep]')")

from agents.benchmark.cluster import ClusterUnavailable, cells, check_reachable  # noqa: E402
from agents.benchmark.policies import parse_policy  # noqa: E402

RAY = Path(sys.executable).with_name("ray")
#: token authentication with this test's own token, for the head and every driver: `ray start --head`
#: turns token authentication on by itself only when ~/.ray/auth_token exists (left by an earlier
#: local Ray), and never makes one, so without this the test depended on what ran before it
AUTH = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
CLI = [sys.executable, "-m", "agents.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def head():
    port = _free_port()
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", **AUTH}
    up = subprocess.run([str(RAY), "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                         "--disable-usage-stats"], capture_output=True, text=True, timeout=180, env=env)
    assert up.returncode == 0, up.stderr[-2000:]
    try:
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([str(RAY), "stop", "--force"], capture_output=True, timeout=120)


def _bench(out: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, **AUTH, "MPLBACKEND": "Agg"}
    cmd = [*CLI, "benchmark", "--tiers", "Hard", "S2", "--policies", "PID", "PROPOSED_KF_DOB@Hard", "PROPOSED@S2",
           "--seeds", "5000000-5000004", "--resamples", "200", "--floors",
           "--out", str(out), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env)


def test_cluster_run_gives_the_local_tables(head, tmp_path):
    local = _bench(tmp_path / "local", "--no-progress")
    assert local.returncode == 0, local.stderr[-3000:]
    remote = _bench(tmp_path / "ray", "--address", head, "--chunk", "2")
    assert remote.returncode == 0, remote.stderr[-3000:]
    assert "cells on" in remote.stderr  # the progress bar counts cells
    a = pd.read_parquet(tmp_path / "local" / "episodes.parquet")
    b = pd.read_parquet(tmp_path / "ray" / "episodes.parquet")
    pd.testing.assert_frame_equal(b, a)  # the same host: the same rows, in the same order
    assert set(a["policy"]) == {"PID", "PROPOSED_KF_DOB", "PROPOSED", "control floor", "oracle-parameter floor"}
    assert len(a) == 2 * 2 * 5 + 2 * 5  # 2 tiers x 2 policies x 5 seeds, and Hard's two floors (none on S2)
    assert (tmp_path / "ray" / "leaderboard.csv").read_text() == (tmp_path / "local" / "leaderboard.csv").read_text()


def test_cells_cover_every_episode_once():
    specs = [parse_policy("PID"), parse_policy("MPC@Hard")]
    seed_map = {"Hard": list(range(10)), "Easy": list(range(20, 27))}
    got = cells(specs, seed_map, 4, floor_tiers=["Hard"])
    pol = [(c[1], c[3].label, s) for c in got if c[0] == "policy" for s in c[4]]
    want = [(t, p.label, s) for t, seeds in seed_map.items() for p in specs if not p.tiers or t in p.tiers
            for s in seeds]
    assert pol == want  # once each, in the local run's order (tier, policy, seed)
    assert [len(c[4]) for c in got if c[0] == "policy" and c[1] == "Easy"] == [4, 3]
    assert [c[:2] for c in got if c[0] == "floors"] == [("floors", "Hard")]


def test_bad_addresses_are_refused_at_once():
    with pytest.raises(ClusterUnavailable, match="not a Ray address"):
        check_reachable("nowhere")
    port = _free_port()  # (nothing listens there)
    with pytest.raises(ClusterUnavailable, match="nothing accepted a connection"):
        check_reachable(f"127.0.0.1:{port}", timeout_s=2)
    out = subprocess.run([*CLI, "benchmark", "--tiers", "Hard", "--policies", "PID", "--seeds", "5000000",
                          "--chunk", "2"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "argument --chunk" in out.stderr
