"""Hardening of the benchmark protocol and its CLI: seed lists, reserved labels, the cache of a
user's controller, output files replaced as one set, write failures, user controllers' errors
and protocol, the sweep's defaults and the benchmark's summary on stdout.

Each defect's test names its reproducer (../shared/reproducers/hardening3/<name>) and uses its
input; the quick seeds are Hard 3000000-3000001.
"""

from __future__ import annotations

import errno
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import agents.benchmark as B
import agents.benchmark.evaluation as BE
import agents.benchmark.outputs as BO
import agents.benchmark.run as BR
from agents.cli import main

ROOT = Path(__file__).resolve().parent.parent
QUICK = ["--tiers", "Hard", "--seeds", "3000000-3000001", "--resamples", "50", "--no-progress"]


def _cli(argv, capsys):
    """(exit code, stdout, stderr lines) of ``auv-follow <argv>`` in-process."""
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err.strip().splitlines()


def _no_work(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("work started before the refusal")

    monkeypatch.setattr(BR, "evaluate_tier", refuse)


def _module(tmp_path, monkeypatch, name, body):
    """A user's controller module ``name`` in tmp_path (importable; removed from sys.modules after)."""
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(body))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    monkeypatch.delitem(sys.modules, name, raising=False)
    return name


HEAD = """\
import numpy as np
class C:
    def __init__(self, spec): pass
    def predict(self, o, state=None, episode_start=None, deterministic=True):
        o = np.asarray(o)
"""


# --- D3 dup_seeds.py: a seed list is a set of episodes -------------------------------------------

def test_repeated_seeds_are_refused_by_the_cli_before_any_work(monkeypatch, capsys):
    """dup_seeds.py: `--seeds 3000000,3000000,3000001` gave 4 rows of seed 3000000 (n^2 per repeat)."""
    _no_work(monkeypatch)
    code, _, err = _cli(["benchmark", "--tiers", "Hard", "--seeds", "3000000,3000000,3000001", "--no-progress",
                         "--policies", "PROPOSED", "--out", "/tmp/never-written"], capsys)
    assert code == 2 and err[-1].startswith("auv-follow benchmark: error: argument --seeds: ")  # argparse's usage first
    assert "repeats seed(s) [3000000]" in err[-1]
    # a range overlapping a list repeats too; evaluate and compare share the parser
    code, _, err = _cli(["evaluate", "runs/none", "--seeds", "5-7,6"], capsys)
    assert code == 2 and "repeats seed(s) [6]" in err[-1]


def test_repeated_seeds_are_refused_by_the_library(monkeypatch):
    """dup_seeds.py's seeds, given to the library functions directly (the floors too)."""
    from agents.benchmark import floors

    seeds = [3000000, 3000000, 3000001]
    with pytest.raises(ValueError, match=r"repeats \[3000000\]"):
        B.benchmark(["PROPOSED"], ["Hard"], seeds=seeds, progress=False)
    with pytest.raises(ValueError, match=r"repeats \[3000000\]"):
        B.benchmark(["PROPOSED"], ["Hard"], seeds={"Hard": seeds}, progress=False)
    with pytest.raises(ValueError, match=r"repeats \[3000000\]"):
        B.evaluate_tier([B.parse_policy("PROPOSED")], "Hard", seeds, progress=False)
    for fn in (floors.floor_episodes, floors.control_floor, floors.information_floor):
        with pytest.raises(ValueError, match=r"repeats \[3000000\]"):
            fn("Hard", seeds)
    # a table that holds one episode twice is refused by the aggregation as well
    ep = pd.DataFrame({"tier": "Hard", "policy": "A", "kind": "classical", "run": "A", "seed": [1, 1, 2],
                       "terminated": False, "true_steady_mean": [0.1, 0.1, 0.2], "true_full_mean": 0.3})
    with pytest.raises(ValueError, match="seed 1 of policy 'A'.*more than once"):
        B.leaderboard(ep, n_resamples=20)


# --- D14 seeds_overflow.py: seeds beyond 64 bits ----------------------------------------------------

def test_a_seed_beyond_64_bits_is_a_one_line_refusal(monkeypatch, capsys):
    """seeds_overflow.py: `--seeds 18446744073709551616` ended in a raw OverflowError (also with --floors)."""
    _no_work(monkeypatch)
    for extra in ([], ["--floors"]):
        code, _, err = _cli(["benchmark", "--tiers", "Hard", "--seeds", str(2**64), "--no-progress",
                             "--policies", "PROPOSED", "--out", "/tmp/never-written", *extra], capsys)
        assert code == 2 and err[-1].startswith("auv-follow benchmark: error: argument --seeds: ")
        assert str(2**64) in err[-1] and "[0, 2**63 - 1]" in err[-1]


def test_seed_range_in_the_library():
    """seeds_overflow.py's seed in the library: the tables store seeds as 64-bit integers, so
    the largest accepted seed is 2**63 - 1 (int64 max) and the next one is refused."""
    from agents.benchmark import floors
    from controllers.evaluation import evaluate

    assert B.check_seed_list([0, 2**63 - 1]) == [0, 9223372036854775807]
    for bad in (2**63, 2**64, -1):
        with pytest.raises(ValueError, match=r"\[0, 2\*\*63 - 1\]"):
            B.check_seed_list([bad])
    with pytest.raises(ValueError, match=str(2**64)):
        B.benchmark(["PROPOSED"], ["Hard"], seeds=[2**64], progress=False)
    with pytest.raises(ValueError, match=str(2**64)):
        floors.floor_episodes("Hard", [2**64])
    with pytest.raises(ValueError, match=str(2**64)):
        evaluate(None, "AUVFollow-Hard-v1", [2**64], progress=False)
    with pytest.raises(ValueError, match="list of integers"):
        B.check_seed_list("3000000")


def test_other_numbers_that_could_overflow_or_never_end(monkeypatch, capsys):
    """--resamples 10**30 was accepted (a bootstrap that never ends); the library checks it too."""
    _no_work(monkeypatch)
    code, _, err = _cli(["benchmark", "--tiers", "Hard", "--resamples", str(10**30), "--policies", "PID",
                         "--out", "/tmp/never-written"], capsys)
    assert code == 2 and "--resamples" in err[-1] and str(B.MAX_RESAMPLES) in err[-1]
    for n in (0, 2**64, 1.5, True):
        with pytest.raises(ValueError, match="n_resamples="):
            B.benchmark(["PID"], ["Hard"], n_resamples=n, progress=False)
    with pytest.raises(ValueError, match="bootstrap_seed="):
        B.benchmark(["PID"], ["Hard"], bootstrap_seed=-1, progress=False)


# --- D5 floor_label_collision.py: the floors' labels are reserved -----------------------------------

@pytest.mark.parametrize("label", ["control floor", "Information  FLOOR", " CONTROL floor"])
def test_floor_labels_are_reserved(label, monkeypatch, capsys, tmp_path):
    """floor_label_collision.py: a policy labelled 'control floor' was merged into the floor's row."""
    _no_work(monkeypatch)
    code, _, err = _cli(["benchmark", *QUICK, "--floors", "--policies", "PROPOSED",
                         f"{label}=examples.user_controller:GoToReference", "--out", str(tmp_path / "never-written")],
                         capsys)
    assert code == 2 and len(err) == 1 and "reserved for the floors" in err[0] and " ".join(label.split()) in err[0]
    with pytest.raises(ValueError, match="reserved"):
        B.benchmark(["PROPOSED", f"{label}=examples.user_controller:GoToReference"], ["Hard"], progress=False)


def test_leaderboard_refuses_a_competitor_with_a_floor_label():
    ep = pd.DataFrame({"tier": "Hard", "policy": ["control floor", "control floor"], "kind": "external",
                       "run": "x", "seed": [1, 2], "terminated": False, "true_steady_mean": [0.1, 0.2],
                       "true_full_mean": 0.3})
    with pytest.raises(ValueError, match="reserved"):
        B.leaderboard(ep, n_resamples=20)
    ep["kind"] = "reference"  # the floors' own rows are fine
    assert B.leaderboard(ep, n_resamples=20)["policy"].tolist() == ["control floor"]


# --- D4 stale_cache_external.py: the cache key covers a user's module ---------------------------------

def test_cache_of_a_module_class_policy_follows_its_source(tmp_path, monkeypatch):
    """stale_cache_external.py: after editing a module:Class policy, --cache returned the old
    code's episodes. The edited module's cached run must equal a fresh run of it (and differ
    from the old code's, which pushes with another constant force)."""
    monkeypatch.setattr(BE, "_code_fingerprint", lambda: "fixed")  # the cache on, whatever git says
    src = HEAD + "        return np.full(o.shape[:-1] + (3,), VALUE), state\n"
    mod = tmp_path / "probe_ctrl_cache.py"
    name = _module(tmp_path, monkeypatch, "probe_ctrl_cache", src.replace("VALUE", "0.0"))
    cache = tmp_path / "cache"

    def run(use_cache):
        sys.modules.pop(name, None)
        res = B.benchmark([f"mine={name}:C"], ["Hard"], seeds=[3000000, 3000001], n_resamples=20, progress=False,
                          cache_dir=cache if use_cache else None)
        return res.episodes["true_steady_mean"].tolist()

    old = run(True)
    assert len(list(cache.glob("*.parquet"))) == 1
    mod.write_text(src.replace("VALUE", "0.75"))
    edited_cached, edited_fresh = run(True), run(False)
    assert edited_cached == edited_fresh and edited_cached != old
    assert len(list(cache.glob("*.parquet"))) == 2  # a new entry for the new source
    assert run(True) == edited_fresh  # and that entry is reused


# --- D12 bench_rename_interrupt.py: the output files are replaced as one set ---------------------------

def _contents(folder):
    """Every entry of ``folder``: a file's bytes, ``"dir"`` for a folder (a left-over temporary one)."""
    return {f.name: f.read_bytes() if f.is_file() else "dir" for f in Path(folder).iterdir()}


def test_ctrl_c_while_the_files_are_renamed_keeps_the_previous_set(tmp_path, monkeypatch, capsys):
    """bench_rename_interrupt.py: a KeyboardInterrupt at the 3rd os.replace into the folder left
    files of the new and of the previous run side by side."""
    out = tmp_path / "bench_ren"
    assert main(["benchmark", *QUICK, "--policies", "PROPOSED", "--out", str(out)]) == 0
    before = _contents(out)
    real, n = os.replace, {"c": 0}

    def patched(src, dst, *a, **k):
        if str(dst).startswith(str(out)) and not str(dst).endswith(".tmp"):
            n["c"] += 1
            if n["c"] == 3:
                raise KeyboardInterrupt
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", patched)
    code, _, err = _cli(["benchmark", "--tiers", "Hard", "--seeds", "3000010-3000011", "--resamples", "50",
                         "--no-progress", "--policies", "PID", "PROPOSED", "--out", str(out)], capsys)
    assert code == 130 and err[-1] == "auv-follow benchmark: interrupted (nothing half-written was kept)"
    assert _contents(out) == before  # every file of the previous run, nothing else
    B.load_result(out)  # and a consistent folder


@pytest.mark.parametrize("fail_at", range(1, 9))
def test_replace_set_is_all_or_nothing_at_every_step(tmp_path, monkeypatch, fail_at):
    """Each of the moves of a three-file set (two previous files aside, three new ones in) failing
    or interrupted: the folder holds exactly the previous files, with an unrelated file untouched."""
    out, stage = tmp_path / "out", tmp_path / "out" / ".stage"
    stage.mkdir(parents=True)
    (out / "a.txt").write_text("old a")
    (out / "b.txt").write_text("old b")
    (out / "report.html").write_text("mine")
    for f in ("a.txt", "b.txt", "c.txt"):
        (stage / f).write_text("new " + f)
    real, n = os.replace, {"c": 0}

    def patched(src, dst, *a, **k):
        n["c"] += 1
        if n["c"] == fail_at:
            raise (KeyboardInterrupt() if fail_at % 2 else OSError(errno.ENOSPC, "No space left on device"))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", patched)
    want = {"a.txt": b"old a", "b.txt": b"old b", "report.html": b"mine"}
    if fail_at <= 5:  # 2 moves aside + 3 moves in
        with pytest.raises(KeyboardInterrupt if fail_at % 2 else B.OutputWriteError):
            B.replace_set(stage, out, ["a.txt", "b.txt", "c.txt"])
        got = {k: v for k, v in _contents(out).items() if not k.startswith(".")}
        assert got == want
        assert not [p for p in out.iterdir() if p.name.startswith(".benchmark-previous-")]
    else:
        B.replace_set(stage, out, ["a.txt", "b.txt", "c.txt"])
        assert (out / "c.txt").read_text() == "new c.txt" and (out / "report.html").read_text() == "mine"


# --- D16 write_errors.sh: read-only --cache, full --out --------------------------------------------------

def test_cache_on_a_read_only_file_system(tmp_path, monkeypatch, capsys):
    """write_errors.sh: `--cache <read-only fs>` ended in a traceback. The CLI refuses it in one
    line before any work; the library, whose cache only saves time, warns and goes on."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if str(p).startswith(str(ro))
                        else real_access(p, mode, *a, **k))
    _no_work(monkeypatch)
    code, _, err = _cli(["benchmark", *QUICK, "--policies", "PROPOSED", "--out", str(tmp_path / "b1"),
                         "--cache", str(ro / "cache")], capsys)
    assert code == 2 and len(err) == 1 and "--cache" in err[0] and "not writable" in err[0]
    monkeypatch.undo()

    def read_only(d, path):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(BE, "_code_fingerprint", lambda: "fixed")
    monkeypatch.setattr(BE, "_write_atomic_parquet", read_only)
    with pytest.warns(UserWarning, match="cannot store episodes there .Read-only file system"):
        res = B.benchmark(["PROPOSED"], ["Hard"], seeds=[3000000, 3000001], n_resamples=20, progress=False,
                          cache_dir=ro / "cache")
    assert len(res.episodes) == 2


def test_out_on_a_full_file_system(tmp_path, monkeypatch, capsys):
    """write_errors.sh: `--out <full fs>` ended in a traceback. Now one line, exit 1, the
    previous files kept, no temporary folder left; a new folder is not left behind empty."""
    out = tmp_path / "b"
    assert main(["benchmark", *QUICK, "--policies", "PROPOSED", "--out", str(out)]) == 0
    before = _contents(out)
    real = BO._write_parquet
    calls = {"n": 0}

    def full(df, path, prov):
        calls["n"] += 1
        if calls["n"] == 2:  # episodes written, traces not
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(df, path, prov)

    monkeypatch.setattr(BO, "_write_parquet", full)
    code, _, err = _cli(["benchmark", *QUICK, "--policies", "PID", "--out", str(out)], capsys)
    assert code == 1 and len(err) == 1
    assert err[0] == f"auv-follow benchmark: error: cannot write into {out} (No space left on device): its previous " \
                     "files are kept"
    assert _contents(out) == before
    calls["n"] = 0
    fresh = tmp_path / "new" / "b"
    code, _, err = _cli(["benchmark", *QUICK, "--policies", "PID", "--out", str(fresh)], capsys)
    assert code == 1 and not fresh.exists()


def test_evaluate_and_compare_writes_fail_in_one_line(tmp_path, monkeypatch, capsys):
    """The same class in the other commands that write: evaluate's CSV and compare's four files
    go through a temporary file / folder; a failed write is one line and keeps the previous files."""
    import agents.benchmark.compare as C
    from agents.cli import _write_csv_atomic

    target = tmp_path / "eval.csv"
    target.write_text("previous\n")

    def full(self, path_or_buf=None, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pd.DataFrame, "to_csv", full)
    with pytest.raises(B.OutputWriteError, match="No space left on device.*previous file is kept"):
        _write_csv_atomic(pd.DataFrame({"a": [1]}), target)
    assert target.read_text() == "previous\n" and [p.name for p in tmp_path.iterdir()] == ["eval.csv"]
    out = tmp_path / "cmp"
    out.mkdir()
    (out / "compare.csv").write_text("previous\n")
    with pytest.raises(B.OutputWriteError, match="previous files are kept"):
        C._write_outputs(out, "compare", pd.DataFrame({"a": [1]}), pd.DataFrame({"a": [1]}), "AUVFollow-S1-v0", [1])
    assert _contents(out) == {"compare.csv": b"previous\n"}
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"repeats \[1000\]"):
        C.compare([], "AUVFollow-S1-v0", [1000, 1000], controllers=["PID"], progress=False)


# --- D19 ext_errors.py: a user's controller that fails is named -------------------------------------

@pytest.mark.parametrize("body,needle", [
    ("        raise RuntimeError('boom')\n", "predict raised RuntimeError: boom"),
    ("        return np.zeros(o.shape[:-1] + (2,)), state\n", "has shape (2, 2), expected (2, 3)"),
    ("        return np.full(o.shape[:-1] + (3,), np.nan), state\n", "seed 3000000, step 1: its action [nan nan nan] "
                                                                   "is not finite"),
    ("        return np.full(o.shape[:-1] + (3,), 'x'), state\n", "has dtype <U1, expected real numbers"),
    ("        return np.zeros(o.shape[:-1] + (3,))\n", "predict returned ndarray, expected a pair (action, state)"),
])
@pytest.mark.parametrize("batched", [True, False])
def test_a_failing_user_controller_is_named(body, needle, batched, tmp_path, monkeypatch, capsys):
    """ext_errors.py: a predict that raises was a raw traceback; a wrong shape gave numpy's
    broadcast message; NaN actions an index into the combined batch. Every message names the
    policy's label, the env, the seed(s), the step and what was wrong."""
    from controllers.evaluation import PolicyError

    name = _module(tmp_path, monkeypatch, f"probe_ext_{abs(hash((body, batched))) % 10**6}", HEAD + body)
    label = "my_probe"
    argv = ["benchmark", *QUICK, "--policies", "PROPOSED", f"{label}={name}:C", "--out", str(tmp_path / "b")]
    code, _, err = _cli(argv + ([] if batched else ["--unbatched"]), capsys)
    assert code == 2 and len(err) == 1 and not (tmp_path / "b").exists()
    assert f"policy '{label}' on AUVFollow-Hard-v1, seed" in err[0]
    if batched or "shape" not in needle:
        assert needle in err[0]
    else:  # one observation at a time: it gets a batch of one
        assert "its action for a batch of one observation, shape (1, 20), has shape (1, 2): expected (1, 3)" in err[0]
    with pytest.raises(PolicyError, match=label):
        B.benchmark(["PROPOSED", f"{label}={name}:C"], ["Hard"], seeds=[3000000, 3000001], n_resamples=20,
                    progress=False, batched=batched)


def test_a_user_controller_that_fails_to_import_or_build_is_named(tmp_path, monkeypatch, capsys):
    """ext_errors.py's other cases: the module raises at import, the class in its constructor."""
    bad_import = _module(tmp_path, monkeypatch, "probe_ext_import", "raise RuntimeError('no import')\n")
    code, _, err = _cli(["benchmark", *QUICK, "--policies", f"mine={bad_import}:C", "--out",
                         str(tmp_path / "b")], capsys)
    assert code == 2 and len(err) == 1
    assert f"'{bad_import}:C'" in err[0] and "raised RuntimeError: no import" in err[0]
    bad_init = _module(tmp_path, monkeypatch, "probe_ext_init", HEAD.replace("pass", "raise KeyError('k')"))
    code, _, err = _cli(["benchmark", *QUICK, "--policies", f"mine={bad_init}:C", "--out",
                         str(tmp_path / "b")], capsys)
    assert code == 2 and len(err) == 1
    assert err[0].endswith(f"policy 'mine' on AUVFollow-Hard-v1: {bad_init}:C(task_spec) raised KeyError: 'k'")


# --- D20 ext_batch_only.py: one protocol ------------------------------------------------------------

BATCH_ONLY = """\
import numpy as np
class C:
    resets = 0
    def __init__(self, spec): self.limits = np.asarray(spec.force_limits)
    def reset(self): type(self).resets += 1
    def predict(self, o, state=None, episode_start=None, deterministic=True):
        o = np.atleast_2d(o)
        assert o.ndim == 2, o.shape
        return np.clip(np.stack([40 * o[:, 12] - 20 * o[:, 0], 40 * o[:, 13] - 20 * o[:, 1],
                                 -3 * o[:, 2]], axis=-1) / self.limits, -1, 1), state
"""


def test_a_batch_only_controller_is_benchmarked_and_replayed(tmp_path, monkeypatch, capsys):
    """ext_batch_only.py: a controller written to docs/benchmark.md's protocol (a batch in, a
    batch out) failed while its replay episode was recorded, with "action has shape (1, 3):
    expected (3,)". Now its replay is in traces.parquet, the unbatched evaluation gives the
    batched numbers, and its optional reset() is called at the start of the episodes."""
    import gymnasium as gym

    from controllers.evaluation import evaluate_batched

    name = _module(tmp_path, monkeypatch, "probe_batch_only", BATCH_ONLY)
    out = tmp_path / "b"
    code, printed, err = _cli(["benchmark", *QUICK, "--policies", "PROPOSED", f"mine={name}:C", "--out", str(out)],
                              capsys)
    assert code == 0, err
    traces = pd.read_parquet(out / "traces.parquet")
    replay = traces[traces["policy"] == "mine"]
    assert len(replay) > 100 and (replay["seed"] == 3000000).all()
    mod = sys.modules[name]
    spec = gym.make("AUVFollow-Hard-v1").unwrapped.task_spec
    direct = evaluate_batched([mod.C(spec)], "AUVFollow-Hard-v1", [3000000, 3000001], progress=False)
    res = B.load_result(out).episodes
    mine = res[res["policy"] == "mine"].reset_index(drop=True)
    assert mine["true_steady_mean"].tolist() == direct["true_steady_mean"].tolist()
    mod.C.resets = 0
    single = B.evaluate_tier([B.parse_policy(f"mine={name}:C")], "Hard", [3000000, 3000001], batched=False,
                             progress=False)
    assert single["true_steady_mean"].to_numpy() == pytest.approx(direct["true_steady_mean"].to_numpy(), rel=1e-9)
    assert mod.C.resets == 2  # one per episode


# --- sweep: output under the ignored folder, one line without ray --------------------------------------

def test_sweep_default_output_is_ignored_by_git():
    """`auv-follow sweep` wrote results/sweeps/, which git did not ignore."""
    from agents.benchmark.sweep import SweepConfig

    storage = SweepConfig().storage
    assert storage == "results/tmp/sweeps"
    probe = f"{storage}/auv-follow-sweep/trials.csv"
    assert subprocess.run(["git", "check-ignore", "-q", probe], cwd=ROOT).returncode == 0
    assert subprocess.run(["git", "check-ignore", "-q", "results/sweeps/x/trials.csv"], cwd=ROOT).returncode == 0


def test_sweep_without_ray_is_one_line_naming_the_extra(tmp_path, monkeypatch, capsys):
    """Without ray the sweep printed a 15-line traceback."""
    for mod in [m for m in sys.modules if m == "ray" or m.startswith("ray.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code, _, err = _cli(["sweep", "--storage", str(tmp_path / "s")], capsys)
    assert code == 1 and err == ['auv-follow sweep: error: Ray Tune is not installed: pip install -e ".[sweep]"']
    assert not (tmp_path / "s").exists()


# --- benchmark: a short summary on stdout --------------------------------------------------------------

def _row(policy, kind, iqm, lo, hi, best="C1"):
    return {"tier": "Hard", "policy": policy, "kind": kind, "true_steady_mean_iqm": iqm,
            "true_steady_mean_iqm_lo": lo, "true_steady_mean_iqm_hi": hi, "best_classical": best}


def test_summary_of_a_hand_made_leaderboard():
    """Top rows by IQM with their CIs, the floors on one line, the best learned against the best
    classical in numbers, and where the files are. By hand: the learned 0.06 against the best
    classical 0.10 is -40.0 % with CIs [0.05, 0.07] and [0.09, 0.11] apart."""
    board = pd.DataFrame([_row("C2", "classical", 0.20, 0.18, 0.22), _row("L1", "learned", 0.06, 0.05, 0.07),
                          _row("C1", "classical", 0.10, 0.09, 0.11), _row("C3", "classical", 0.30, 0.28, 0.33),
                          _row("C4", "classical", 0.40, 0.38, 0.43),
                          _row("oracle-parameter floor", "reference", 0.01, 0.01, 0.01)])
    files = {k: Path("/r/b") / n for k, n in BO.OUTPUT_FILES.items()}
    text = B.benchmark_summary(board, files, top=3)
    lines = text.splitlines()
    assert lines[0] == "Hard: 5 policies by steady_mean error IQM [95 % CI] in m; best classical C1"
    assert lines[1].split() == ["1.", "L1", "0.0600", "[0.0500,", "0.0700]", "(learned)"]
    assert lines[2].split() == ["2.", "C1", "0.1000", "[0.0900,", "0.1100]", "(classical)"]
    assert lines[3].split() == ["3.", "C2", "0.2000", "[0.1800,", "0.2200]", "(classical)"]
    assert lines[4].strip() == "... 2 more in the full table"
    assert lines[5].strip() == "floors: oracle-parameter floor 0.0100 [0.0100, 0.0100]"
    assert lines[6].strip() == "best learned L1: -40.0 % against the best classical C1, 95 % CIs apart"
    assert not re.search(r"\b(goal|met)\b", text)  # the numbers, not a verdict on our plans
    assert lines[7].startswith("full table: /r/b/leaderboard.md (and episodes.parquet") and len(lines) == 8
    board.loc[1, "true_steady_mean_iqm_hi"] = 0.095  # CIs overlap
    assert "L1: -40.0 % against the best classical C1, 95 % CIs overlap" in B.benchmark_summary(board)
    # a learned policy clearly worse (0.13 [0.12, 0.14] against [0.09, 0.11]): apart
    board.loc[1, ["true_steady_mean_iqm", "true_steady_mean_iqm_lo", "true_steady_mean_iqm_hi"]] = [0.13, 0.12, 0.14]
    assert "L1: +30.0 % against the best classical C1, 95 % CIs apart" in B.benchmark_summary(board)


def test_cli_prints_a_short_summary(tmp_path, capsys):
    """`auv-follow benchmark` printed all of leaderboard.md (about 60 lines of provenance JSON)
    and a raw goal_check dict."""
    out = tmp_path / "b"
    code, printed, _ = _cli(["benchmark", *QUICK, "--policies", "PID", "PROPOSED", "--out", str(out)], capsys)
    lines = printed.strip().splitlines()
    assert code == 0 and len(lines) <= 6
    assert lines[0].startswith("Hard: 2 policies by steady_mean error IQM")
    board = pd.read_csv(out / "leaderboard.csv", comment="#").sort_values("true_steady_mean_iqm")
    best = board.iloc[0]
    assert lines[1].split()[:3] == ["1.", best["policy"], f"{best['true_steady_mean_iqm']:.4f}"]
    assert lines[-1].startswith(f"full table: {out / 'leaderboard.md'}")
    assert "provenance" not in printed and "{" not in printed and "git_commit" not in printed
    assert json.loads((out / "benchmark.json").read_text())["config"]["seeds"] == {"Hard": [3000000, 3000001]}
    assert np.isfinite(board["true_steady_mean_iqm"]).all()
