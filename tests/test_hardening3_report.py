"""Hardening III, the report (``auv-follow report``, agents/benchmark/report.py).

Defect map (reproducers in ../shared/reproducers/hardening3/): D1 report_partial_symlink.py ->
test_partial_name_link_is_never_written_through (and the other writes: test_link_at_the_page_is_replaced_not_followed,
test_interrupted_write_leaves_the_old_page_and_no_temporary_file); D2 report_symlink_outside.py ->
test_link_out_of_the_folder_is_refused (every file the report reads), test_link_inside_the_folder_is_read;
D15 report_tracebacks.py -> test_malformed_files_are_one_line_naming_file_and_column (and the same class for
every column the page uses: test_every_checked_column_is_refused_in_one_line); D21 report_unnamed_errors.py ->
test_bad_seeds_name_the_file_and_the_column. The page itself (one colour per policy, families by hue, the best
few drawn, every column explained, one heading per section): the test_page_* and test_styles_* tests.
"""

from __future__ import annotations

import colorsys
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

import agents.benchmark.report as R
from agents.benchmark.report import write_report
from agents.benchmark.run import benchmark
from agents.cli import main

SEEDS = [3000000, 3000001]  # the reproducers' quick-look seeds (Hard)


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    """The reproducers' folder: `benchmark --tiers Hard --seeds 3000000-3000001 --resamples 50 --policies PROPOSED`."""
    out = tmp_path_factory.mktemp("bench")
    benchmark(["PROPOSED"], ["Hard"], seeds=SEEDS, out_dir=out, n_resamples=50, progress=False)
    return out


def _stripped(bench: Path, dst: Path) -> Path:
    """A copy without provenance stamps (a folder from elsewhere: load_result's mixed-run check
    passes whatever the files hold), as the reproducers make it."""
    shutil.copytree(bench, dst)
    for f in ("episodes.parquet", "traces.parquet"):
        t = pq.read_table(dst / f)
        pq.write_table(t.replace_schema_metadata({}), dst / f)
    pd.read_csv(dst / "leaderboard.csv", comment="#").to_csv(dst / "leaderboard.csv", index=False)
    prov = json.loads((dst / "benchmark.json").read_text())
    prov.pop("files", None)  # (and no checksum of the CSV)
    (dst / "benchmark.json").write_text(json.dumps(prov))
    return dst


def _report_cli(folder: Path, capsys) -> tuple[int, list[str]]:
    """`auv-follow report --bench folder`: (exit code, stderr lines); never an escaped exception."""
    try:
        code = main(["report", "--bench", str(folder)])
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr().err.strip().splitlines()


# --- D1: the temporary page is created afresh, never written through a name already there ----------

def test_partial_name_link_is_never_written_through(bench, tmp_path, capsys):
    """report_partial_symlink.py: a link `.report.html.partial` -> a file outside the folder; the report is
    written, the outside file keeps its content, and no temporary file is left behind."""
    b = _stripped(bench, tmp_path / "b")
    victim = tmp_path / "victim.txt"
    victim.write_text("ORIGINAL\n")
    (b / ".report.html.partial").symlink_to(victim)
    code, err = _report_cli(b, capsys)
    assert code == 0, err
    assert victim.read_text() == "ORIGINAL\n"
    page = b / "report.html"
    assert page.is_file() and not page.is_symlink() and "<!DOCTYPE html>" in page.read_text()
    assert sorted(p.name for p in b.iterdir() if p.name.endswith(".partial")) == [".report.html.partial"]


def test_link_at_the_page_is_replaced_not_followed(bench, tmp_path):
    """The same class at the page's own name: report.html is a link to a file outside; the link is replaced
    by the page and the outside file is untouched."""
    b = _stripped(bench, tmp_path / "b")
    victim = tmp_path / "victim.txt"
    victim.write_text("ORIGINAL\n")
    (b / "report.html").symlink_to(victim)
    path = write_report(b)
    assert victim.read_text() == "ORIGINAL\n"
    assert path == b / "report.html" and not path.is_symlink() and "<!DOCTYPE html>" in path.read_text()


def test_interrupted_write_leaves_the_old_page_and_no_temporary_file(bench, tmp_path, monkeypatch):
    b = _stripped(bench, tmp_path / "b")
    (b / "report.html").write_text("OLD PAGE")
    before = sorted(p.name for p in b.iterdir())

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(R.os, "replace", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_report(b)
    assert (b / "report.html").read_text() == "OLD PAGE"
    assert sorted(p.name for p in b.iterdir()) == before


@pytest.mark.parametrize("where", ["mkstemp", "replace"])
def test_failed_write_is_one_line_and_keeps_the_old_page(bench, tmp_path, monkeypatch, capsys, where):
    """A full disk (ENOSPC) when the temporary page is created or renamed: one line naming the page, the old
    page unchanged, no temporary file left."""
    import errno

    b = _stripped(bench, tmp_path / "b")
    (b / "report.html").write_text("OLD PAGE")
    before = sorted(p.name for p in b.iterdir())

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(R.tempfile if where == "mkstemp" else R.os, where, full)
    code, err = _report_cli(b, capsys)
    assert code == 2 and len(err) == 1, err
    assert f"cannot write the report {b / 'report.html'}: No space left on device" in err[0]
    assert (b / "report.html").read_text() == "OLD PAGE" and sorted(p.name for p in b.iterdir()) == before


def test_page_file_mode_follows_the_umask(bench, tmp_path):
    """An ordinary new file (rw-r--r-- under umask 022), not the private mode of a temporary file."""
    import os

    b = _stripped(bench, tmp_path / "b")
    old = os.umask(0o022)
    try:
        path = write_report(b)
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644


def test_out_that_is_a_directory_is_refused(bench, tmp_path):
    with pytest.raises(ValueError, match="is a directory"):
        write_report(bench, tmp_path)


# --- D2: only the folder's own files are read ---------------------------------------------------------

@pytest.mark.parametrize("name", ["benchmark.json", "leaderboard.csv", "episodes.parquet", "traces.parquet"])
def test_link_out_of_the_folder_is_refused(bench, tmp_path, capsys, name):
    """report_symlink_outside.py: benchmark.json is a link to an outside JSON with a 'config' key and a secret;
    the report is refused in one line naming the file, and no page is written (the same for each file read)."""
    b = _stripped(bench, tmp_path / "b")
    outside = tmp_path / f"outside-{name}"
    if name == "benchmark.json":
        outside.write_text(json.dumps({"config": {}, "token": "SECRET-TOKEN-123"}))
    else:
        shutil.copy(b / name, outside)
    (b / name).unlink()
    (b / name).symlink_to(outside)
    code, err = _report_cli(b, capsys)
    assert code == 2 and len(err) == 1, err
    assert f"{b / name} is a symbolic link to {outside}" in err[0] and "outside" in err[0]
    assert not (b / "report.html").exists()


def test_link_inside_the_folder_is_read(bench, tmp_path):
    """A link to a file inside the folder is the folder's own file: read as usual."""
    b = _stripped(bench, tmp_path / "b")
    (b / "kept").mkdir()
    (b / "benchmark.json").rename(b / "kept" / "benchmark.json")
    (b / "benchmark.json").symlink_to(Path("kept") / "benchmark.json")
    assert "<!DOCTYPE html>" in write_report(b).read_text()


# --- D15, D21: malformed files: one line naming the file and the column --------------------------------

def _few_cols(d: Path) -> None:
    lb = pd.read_csv(d / "leaderboard.csv")
    lb[["tier", "policy", "kind", "true_steady_mean_iqm", "true_steady_mean_iqm_lo",
        "true_steady_mean_iqm_hi"]].to_csv(d / "leaderboard.csv", index=False)


def _str_num(d: Path) -> None:
    lb = pd.read_csv(d / "leaderboard.csv").astype({"true_steady_mean_iqm": object})
    lb.loc[0, "true_steady_mean_iqm"] = "x"
    lb.to_csv(d / "leaderboard.csv", index=False)


def _huge(d: Path) -> None:
    t = pd.read_parquet(d / "traces.parquet")
    t.assign(follower_x=1e308, F_u=-1e308, time=1e308).to_parquet(d / "traces.parquet", index=False)


def _deep(d: Path) -> None:
    (d / "benchmark.json").write_text('{"config": ' + "[" * 100000 + "]" * 100000 + "}")


@pytest.mark.parametrize("make,needles", [
    (_few_cols, ["leaderboard.csv lacks columns", "'runs'", "'episodes'", "'termination_rate'"]),
    (_str_num, ["leaderboard.csv column 'true_steady_mean_iqm' is not a number: 'x' in row 1",
                "policy 'PROPOSED'"]),
    (_huge, ["traces.parquet", "column 'time'", "1e+09"]),
    (_deep, ["benchmark.json nests its JSON too deeply"]),
], ids=["few_cols", "str_num", "huge_traces", "deep_json"])
def test_malformed_files_are_one_line_naming_file_and_column(bench, tmp_path, capsys, make, needles):
    """report_tracebacks.py: only the 6 columns load_result requires (was KeyError 'best_classical'), a string
    in a numeric column (TypeError), traces of 1e308 (ZeroDivisionError), benchmark.json nested 100000 deep
    (RecursionError): each a one-line refusal (exit 2) naming the file, and the column where there is one."""
    b = _stripped(bench, tmp_path / "b")
    make(b)
    code, err = _report_cli(b, capsys)
    assert code == 2 and len(err) == 1, err
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    assert not (b / "report.html").exists()


@pytest.mark.parametrize("fill,needle", [
    ("nan", "episodes.parquet column 'seed' is missing (NaN): 'nan' in row 1 (tier 'Hard', policy 'PROPOSED')"),
    ("str", "episodes.parquet column 'seed' is not a number: '3000000x' in row 1"),
], ids=["seed_nan", "seed_str"])
def test_bad_seeds_name_the_file_and_the_column(bench, tmp_path, capsys, fill, needle):
    """report_unnamed_errors.py: NaN seeds ('cannot convert float NaN to integer') and non-numeric seeds
    ("invalid literal for int()") in episodes.parquet: the message names the file, the column and the row."""
    b = _stripped(bench, tmp_path / "b")
    e = pd.read_parquet(b / "episodes.parquet")
    e = e.assign(seed=e.seed.astype(str) + "x") if fill == "str" else e.assign(seed=np.nan)
    e.to_parquet(b / "episodes.parquet", index=False)
    code, err = _report_cli(b, capsys)
    assert code == 2 and len(err) == 1, err
    assert needle in err[0], err[0]


def _edit(name: str, fn):
    def make(d: Path) -> None:
        p = d / name
        if name.endswith(".csv"):
            fn(pd.read_csv(p)).to_csv(p, index=False)
        elif name.endswith(".parquet"):
            fn(pd.read_parquet(p)).to_parquet(p, index=False)
        else:
            p.write_text(fn(p.read_text()))
    return make


def _policies(value) -> callable:
    def fn(text: str) -> str:
        prov = json.loads(text)
        prov["config"]["policies"] = value
        return json.dumps(prov)
    return fn


@pytest.mark.parametrize("make,needle", [
    (_edit("leaderboard.csv", lambda b: b.assign(runs=-1)), "leaderboard.csv column 'runs' is negative: '-1'"),
    (_edit("leaderboard.csv", lambda b: b.assign(runs=1.5)), "column 'runs' is not a whole number: '1.5'"),
    (_edit("leaderboard.csv", lambda b: b.assign(episodes=1e300)), "column 'episodes' is not below 1e+100"),
    (_edit("leaderboard.csv", lambda b: pd.concat([b, b])), "has two rows for policy 'PROPOSED' on tier 'Hard'"),
    (_edit("leaderboard.csv", lambda b: b.iloc[:0]), "leaderboard.csv has no rows"),
    (_edit("leaderboard.csv", lambda b: b.assign(tier="Nope")), "leaderboard.csv column 'tier': tier='Nope'"),
    (_edit("leaderboard.csv", lambda b: b.assign(policy=np.nan)), "column 'policy' is empty in row 1"),
    (_edit("leaderboard.csv", lambda b: b.assign(true_steady_mean_iqm=np.inf)), "'true_steady_mean_iqm' is infinite"),
    (_edit("leaderboard.csv", lambda b: b.assign(true_steady_mean_iqm=-1.0)), "'true_steady_mean_iqm' is negative"),
    (_edit("leaderboard.csv", lambda b: b.assign(termination_rate=True)), "'termination_rate' holds booleans"),
    (_edit("episodes.parquet", lambda e: e.assign(terminated=e.terminated.astype(str))),
     "episodes.parquet column 'terminated' is not true/false (or 1/0): 'False'"),
    (_edit("episodes.parquet", lambda e: e.assign(cond_latency_s="x")), "column 'cond_latency_s' is not a number"),
    (_edit("episodes.parquet", lambda e: e.assign(cond_loss_prob=np.inf)), "column 'cond_loss_prob' is infinite"),
    (_edit("episodes.parquet", lambda e: e.drop(columns=["terminated"])), "episodes.parquet lacks columns"),
    (_edit("traces.parquet", lambda t: t.assign(seed="s")), "traces.parquet column 'seed' is not a number: 's'"),
    (_edit("traces.parquet", lambda t: t.assign(time=1.0)), "column 'time' does not increase"),
    (_edit("traces.parquet", lambda t: t.assign(F_u="q")), "column 'F_u' is not a number: 'q'"),
    (_edit("traces.parquet", lambda t: t.drop(columns=["time"])), "lacks columns ['time']"),
    (_edit("benchmark.json", _policies(5)), "benchmark.json config.policies is a int: a list of policies"),
    (_edit("leaderboard.csv", lambda b: b), None),  # (the unedited copy is fine)
])
def test_every_checked_column_is_refused_in_one_line(bench, tmp_path, capsys, make, needle):
    """The class of D15/D21 for every column and file the page uses: a one-line refusal naming it."""
    b = _stripped(bench, tmp_path / "b")
    make(b)
    code, err = _report_cli(b, capsys)
    if needle is None:
        assert code == 0, err
        return
    assert code == 2 and len(err) == 1, err
    assert needle in err[0], err[0]


def test_wrong_argument_types_are_type_errors(bench):
    with pytest.raises(TypeError, match="replay_seed='3000000'"):
        write_report(bench, replay_seed="3000000")
    with pytest.raises(TypeError, match="replay_seed=True"):
        write_report(bench, replay_seed=True)
    with pytest.raises(TypeError, match="time_policies='PROPOSED'"):
        write_report(bench, time_policies="PROPOSED")
    with pytest.raises(TypeError, match="replay_tier=3"):
        write_report(bench, replay_tier=3)
    with pytest.raises(TypeError, match="bench_dir=None"):
        write_report(None)


def test_breakdown_leaves_out_missing_conditions_and_refuses_bad_ones():
    """binned_breakdown: NaN conditions are left out (by hand: the two others, one per bin); text is refused."""
    ep = pd.DataFrame({"policy": "A", "terminated": False, "true_steady_mean": [1.0, 2.0, 3.0],
                       "cond_latency_s": [0.0, np.nan, 1.0]})
    bd = R.binned_breakdown(ep, "cond_latency_s", bins=2)
    assert bd["bin_center"].tolist() == pytest.approx([0.25, 0.75]) and bd["iqm"].tolist() == [1.0, 3.0]
    with pytest.raises(ValueError, match="'cond_latency_s' is not a number: 'x'"):
        R.binned_breakdown(ep.assign(cond_latency_s="x"), "cond_latency_s")
    with pytest.raises(ValueError, match="bins=0"):
        R.binned_breakdown(ep, "cond_latency_s", bins=0)


# --- the page: colours, families, the best few drawn, the columns explained ----------------------------

def _board(rows: dict[str, list[tuple[str, str, float]]]) -> pd.DataFrame:
    """A leaderboard of (policy, kind, steady IQM) per tier, every other column filled in."""
    out = []
    for tier, items in rows.items():
        for p, kind, v in items:
            r = {"tier": tier, "policy": p, "kind": kind, "runs": 1, "episodes": 100, "termination_rate": 0.0,
                 "best_classical": "A"}
            for m in ("true_steady_mean", "true_full_mean"):
                for s in ("iqm", "mean"):
                    r.update({f"{m}_{s}": v, f"{m}_{s}_lo": 0.9 * v, f"{m}_{s}_hi": 1.1 * v})
            out.append(r)
    return R._checked_board(pd.DataFrame(out), "leaderboard.csv")


def _hue(color: str) -> tuple[float, float]:
    h, _, s = colorsys.rgb_to_hls(*(int(color[i:i + 2], 16) / 255 for i in (1, 3, 5)))
    return 360 * h, s


def test_styles_one_colour_per_policy_by_family_and_rank():
    """Two tiers. Classical by IQM: T1 A<B<C<D<E, T2 A<D<B<C<E -> drawn A, B, C (T1) and D (T2), E hidden.
    Learned: T1 L1<L2<L3<L4<L5, T2 only L5<L6 -> drawn L1-L3 and L5, L6; L4 hidden. Floors: the information
    floor drawn, the control floor hidden. Families by hue: floors grey, classical warm (red-orange-gold),
    learned cool (green-blue-violet), an unknown kind magenta; all colours distinct."""
    c = [("A", 0.1), ("B", 0.2), ("C", 0.3), ("D", 0.4), ("E", 0.5)]
    t2 = {"A": 0.1, "D": 0.2, "B": 0.3, "C": 0.4, "E": 0.5}
    board = _board({
        "T1": [("control floor", "reference", 0.001), ("oracle-parameter floor", "reference", 0.05),
               *((p, "classical", v) for p, v in c),
               *((f"L{k}", "learned", 0.1 + 0.1 * k) for k in range(1, 6)), ("X", "<b>odd kind</b>", 0.3)],
        "T2": [("control floor", "reference", 0.001), ("oracle-parameter floor", "reference", 0.05),
               *((p, "classical", v) for p, v in t2.items()), ("L5", "learned", 0.2), ("L6", "learned", 0.3)]})
    st = R._policy_styles(board)
    assert {p for p, s in st.items() if s.shown} == {"oracle-parameter floor", "A", "B", "C", "D", "L1", "L2", "L3",
                                                      "L5", "L6", "X"}
    colors = [s.color for s in st.values()]
    assert len(set(colors)) == len(colors)
    for p, s in st.items():
        hue, sat = _hue(s.color)
        if p.endswith("floor"):
            assert sat == 0 and s.family == "floor"
        elif p in "ABCDE":
            assert (hue <= 60 or hue >= 345) and s.family == "classical", (p, s.color, hue)
        elif p.startswith("L"):
            assert 90 <= hue <= 280 and s.family == "learned", (p, s.color, hue)
        else:
            assert 295 <= hue <= 340 and s.family == "other", (p, s.color, hue)
    # legend order: floors, classical, learned, other; best first within a family
    order = sorted(st, key=lambda p: st[p].rank)
    assert order[:2] == ["control floor", "oracle-parameter floor"] and order[2:7] == ["A", "B", "D", "C", "E"]
    assert order[-1] == "X"
    # the default-drawn policies of a tier are told apart by their colours (the floors also by dashes)
    for tier in ("T1", "T2"):
        drawn = [st[p].color for p in board.loc[board["tier"] == tier, "policy"] if st[p].shown
                 and st[p].family != "floor"]
        gaps = [R._distance(a, b) for i, a in enumerate(drawn) for b in drawn[i + 1:]]
        assert min(gaps) >= R._DISTINCT


def test_styles_beyond_the_palette_stay_unique():
    board = _board({"T": [(f"P{k}", "learned", 0.01 * (k + 1)) for k in range(60)]})
    colors = [s.color for s in R._policy_styles(board).values()]
    assert len(set(colors)) == 60


def test_many_learned_policies_on_one_tier_keep_distinct_colours():
    """Eighteen learned and eight classical policies on one tier (Easy's count of the committed
    leaderboard, plus eight): any two, drawn by default or not, differ by at least 90 in the
    redmean distance. With only the family's 28-colour palette to pick from, the greedy choice
    left two learned colours 52 apart on the committed board."""
    import itertools

    board = _board({"T": [*((f"C{k}", "classical", 0.02 + 0.001 * k) for k in range(8)),
                          *((f"L{k}", "learned", 0.03 + 0.001 * k) for k in range(18))]})
    st = R._policy_styles(board)
    worst = min((R._distance(st[p].color, st[q].color), p, q) for p, q in itertools.combinations(st, 2))
    assert worst[0] >= 90, worst


def test_long_legend_entries_are_wrapped_and_their_rows_get_the_room():
    """A 130-character label becomes lines of at most LEGEND_WIDTH characters joined by <br>, its
    words in order; the legend is as tall as its rows: 22 px for a one-line row, 15 px for each
    extra line of the row's longest entry, plus 30 px (by hand, three columns: a first row of
    entries with 1, 3 and 1 lines, 22 + 2 * 15 = 52 px, a second of one line, 22 px; 52 + 22 + 30 = 104)."""
    label = " ".join(["PPO scratch + privileged critic, action-rate 0.3, yaw moment from PROPOSED_KF_DOB"] * 2)[:130]
    name = R._legend_name(label)
    lines = name.split("<br>")
    assert len(lines) > 1 and all(len(line) <= R.LEGEND_WIDTH for line in lines)
    assert " ".join(lines) == label.replace("&", "&amp;")
    three = "<br>".join(["x"] * 3)
    assert R._legend(["a", three, "b", "c"], columns=3)[1] == 104
    assert R._legend(["a", "b"], columns=3)[1] == 22 + 30


def test_gap_closed_is_explained_with_the_folder_own_numbers():
    """Information floor 0.0173, best classical 0.0186, a policy at 0.5: gap closed = (0.0186 - 0.5) /
    (0.0186 - 0.0173) = -0.4814 / 0.0013 = -370.31 (by hand); the page says what it is and why it is so low."""
    board = _board({"Easy": [("oracle-parameter floor", "reference", 0.0173), ("A", "classical", 0.0186),
                             ("B", "classical", 0.5)]})
    board["gap_closed"] = [np.nan, 0.0, (0.0186 - 0.5) / (0.0186 - 0.0173)]
    text = R._columns_html(board, gap=True, has_base=False)
    assert "<dt>gap closed [-]</dt>" in text and "very negative" in text
    assert "only 0.0013 m above the oracle-parameter floor (0.0173 m)" in text and "-370.31" in text


def test_page_explains_every_column_once_and_has_one_heading_per_section(bench, tmp_path):
    b = _stripped(bench, tmp_path / "b")
    page = write_report(b).read_text()
    body = page.split("</script></head>")[1]
    heads = set(re.findall(r"<th>(.*?)</th>", body))
    explained = re.findall(r"<dt>(.*?)</dt>", body)
    assert heads and heads <= set(explained), heads - set(explained)
    h2 = re.findall(r"<h2[^>]*>(.*?)</h2>", body)
    assert len(h2) == len(set(h2)) and h2.count("Leaderboard") == 1
    # self-contained: plotly.js inline, nothing fetched
    assert not re.search(r"<script[^>]*\bsrc=", page) and "<link rel='stylesheet'" not in page
    assert "https://cdn" not in body


def test_every_policy_on_a_tier_has_a_colour_far_from_the_others():
    """On the committed leaderboard (15 policies on Easy), any two policies that share a tier,
    floors aside (they are dashed), differ by at least 60 in the redmean distance (two blues such
    as #2b8cbe and #3288bd are 14 apart) whether or not they are drawn by default."""
    import itertools

    from agents.benchmark.report import _checked_board, _distance, _policy_styles

    assert _distance("#2b8cbe", "#3288bd") < 20  # the pair the rule exists for
    root = Path(__file__).resolve().parents[1]
    board = _checked_board(pd.read_csv(root / "results" / "benchmark" / "leaderboard.csv", comment="#"), "board")
    styles = _policy_styles(board)
    for tier, sub in board.groupby("tier"):
        cols = [(p, styles[p].color) for p in sub["policy"] if styles[p].family != "floor"]
        worst = min((_distance(a, b), p, q) for (p, a), (q, b) in itertools.combinations(cols, 2))
        assert worst[0] >= 60, (tier, worst)
