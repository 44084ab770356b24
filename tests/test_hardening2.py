"""Hardening II (CHANGELOG.md, 0.2.0): each test takes the input of a reproducer in
/work/shared/reproducers (named in its docstring) and asserts the fixed behaviour.

Item map: 1 xss_kind_tier.sh -> test_report_escapes_every_value_from_the_folder,
test_markdown_escapes_labels; 2 report_unpickle.sh -> test_report_never_loads_a_model_file;
3 -> test_policy_kwargs_*; 4 -> test_sweep_name_cannot_leave_storage; 5 stale_cache.sh ->
test_cache_key_*, test_broken_cache_entry_*; 6 p2_partial_write.py -> test_interrupted_write_*,
test_mixed_folder_is_refused; 7 default_out_overwrite.sh -> test_benchmark_without_out_*;
8 interrupted_run_in_benchmark.sh -> test_interrupted_run_is_refused, and
test_statistics_contradicting_config_are_refused, p1_forces2.py -> test_force_limits_*,
test_accepted_large_force_limits_stay_finite, test_scenario_on_a_tier_id_is_refused;
9 p1_mixed.py, p1_mixed_autoreset.py, p1_partial_reset.py -> test_ranges_that_can_draw_*,
test_ranges_whose_every_draw_is_valid_*; 10 -> test_refusals_are_one_line_*, test_ctrl_c_*,
test_sweep_failures_*, test_corrupt_file_*, test_config_error_*, test_compare_of_a_v1_agent_*,
test_training_on_the_ood_tier_warns; 11 -> test_user_controller_*; 13 ->
test_default_seeds_*; 15 -> test_extreme_overlaps_hard_*; 17 -> test_help_*,
test_expected_files; 1 in a browser -> test_xss_report_runs_no_script_in_a_browser.
"""

from __future__ import annotations

import base64
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import yaml

import agents.benchmark as B
import agents.benchmark.evaluation as BE
import agents.benchmark.outputs as BO
import agents.benchmark.run as BR
from agents.benchmark.outputs import load_result
from agents.benchmark.policies import parse_policy
from agents.benchmark.report import write_report
from agents.benchmark.run import benchmark
from agents.cli import main

ROOT = Path(__file__).resolve().parents[1]
LEARNED_RUN = ROOT / "results" / "benchmark" / "runs" / "ppo-scratch" / "ppo-Hard-scratch-seed0"
SEEDS = [3000000, 3000001]  # the reproducers' quick-look seeds (Hard)
XSS = "<img src=x onerror=alert('kind')>"


@pytest.fixture(scope="module")
def run_copy(tmp_path_factory) -> Path:
    """A copy of a committed finished run (the reproducers' runs/tiny)."""
    dst = tmp_path_factory.mktemp("runs") / "tiny"
    shutil.copytree(LEARNED_RUN, dst, ignore=shutil.ignore_patterns("checkpoints", "tb", "monitor", "eval"))
    return dst


@pytest.fixture(scope="module")
def bench(tmp_path_factory, run_copy) -> Path:
    """`benchmark --tiers Hard --seeds 3000000-3000001 --resamples 50 --policies PROPOSED L=<run>`."""
    out = tmp_path_factory.mktemp("bench")
    benchmark(["PROPOSED", f"L={run_copy}"], ["Hard"], seeds=SEEDS, out_dir=out, n_resamples=50, progress=False)
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _unseal(folder: Path) -> None:
    """Drop the SHA-256 of leaderboard.csv from benchmark.json: a hand-made CSV, as the reproducers
    write it (a sealed folder refuses an edited CSV)."""
    prov = json.loads((folder / "benchmark.json").read_text())
    prov.pop("files", None)
    (folder / "benchmark.json").write_text(json.dumps(prov))


# --- item 1: escaping ---------------------------------------------------------------------------

def test_report_escapes_every_value_from_the_folder(bench, tmp_path):
    """xss_kind_tier.sh: kind of a row and tier of an added row set to <img onerror>; a policy label
    that plotly would render as a link."""
    b = _copy(bench, tmp_path / "b")
    _unseal(b)
    p = b / "leaderboard.csv"
    lines = p.read_text().splitlines()
    head = lines[0].split(",")
    row = lines[1].split(",")
    row[head.index("kind")] = f'"{XSS}"'
    lines[1] = ",".join(row)
    row2 = list(row)
    row2[head.index("tier")] = "\"<img src=x onerror=alert('tier')>\""
    lines.append(",".join(row2))
    row3 = list(lines[3].split(","))
    row3[head.index("policy")] = '"<a href=""javascript:alert(1)"">click</a>"'
    lines.append(",".join(row3))
    p.write_text("\n".join(lines) + "\n")
    page = write_report(b).read_text()
    assert "<img src=x" not in page and "<a href=" not in page.split("<script")[0]
    assert "&lt;img src=x onerror=alert(&#x27;kind&#x27;)&gt;" in page  # shown as text in the table
    assert "&lt;img src=x onerror=alert(&#x27;tier&#x27;)&gt;" in page
    # plotly renders a subset of HTML in labels: the label reaches it with its '<' as an entity
    assert "javascript:alert(1)" in page and "\\u003ca href" not in page and "&lt;a href=" in page


def test_markdown_escapes_labels():
    """leaderboard.md: a label with HTML or a '|' stays text in one cell."""
    board = pd.DataFrame([{"tier": "Hard", "policy": "<script>x</script>|y", "kind": "learned", "runs": 1,
                           "episodes": 2, "best_classical": None, "termination_rate": 0.0,
                           **{f"{m}_{s}{b}": 1.0 for m in B.LEADERBOARD_METRICS for s in ("iqm", "mean")
                              for b in ("", "_lo", "_hi")},
                           "true_steady_mean_iqm_change_pct": float("nan"), "poi": float("nan"),
                           "poi_lo": float("nan"), "poi_hi": float("nan")}])
    md = B.leaderboard_markdown(board, {"config": {"command": "auv-follow benchmark --policies 'a```b'"}})
    assert "<script>" not in md and "&lt;script&gt;x&lt;/script&gt;\\|y" in md
    row = next(line for line in md.splitlines() if "script" in line and line.startswith("|"))
    assert row.count(" | ") + 2 == row.count("|") - row.count("\\|")  # the label's '|' is not a cell border
    assert "\n````json\n" in md  # a fence longer than the backticks inside


# --- item 2: report from the stored tables alone -------------------------------------------------

def _evil_model(run: Path, marker: Path) -> None:
    """p3_evil_model.py: model.zip whose 'data' has a cloudpickled entry that creates marker on load."""

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    src = run / "model.zip"
    zin = zipfile.ZipFile(src)
    data = json.loads(zin.read("data"))
    data["lr_schedule"][":serialized:"] = base64.b64encode(pickle.dumps(Evil())).decode()
    tmp = run / "evil.zip"
    with zipfile.ZipFile(tmp, "w") as zout:
        for item in zin.infolist():
            zout.writestr(item, json.dumps(data) if item.filename == "data" else zin.read(item.filename))
    zin.close()
    tmp.replace(src)


def test_report_never_loads_a_model_file(bench, run_copy, tmp_path, monkeypatch):
    """report_unpickle.sh: benchmark.json points the learned policy at a run whose model.zip runs a
    command when unpickled; the report is built and the command never runs."""
    evil = _copy(run_copy, tmp_path / "evil_run")
    marker = tmp_path / "PWNED_report"
    _evil_model(evil, marker)
    b = _copy(bench, tmp_path / "b")
    prov = json.loads((b / "benchmark.json").read_text())
    prov.pop("files", None)  # (the CSV is rewritten below: no checksum)
    for p in prov["config"]["policies"]:
        if p["kind"] == "learned":
            p["runs"] = [str(evil)]
    # keep the folder consistent (else it is refused as mixed): rewrite every stamp alike
    (b / "benchmark.json").write_text(json.dumps(prov, indent=1))
    res = load_result(bench)
    BO._write_parquet(res.episodes, b / "episodes.parquet", prov)
    BO._write_csv(res.leaderboard, b / "leaderboard.csv")
    BO._write_parquet(res.traces, b / "traces.parquet", prov)
    import agents.training.loading

    def no_load(*a, **k):
        raise AssertionError("report loaded a model")

    monkeypatch.setattr(agents.training.loading, "load_agent", no_load)
    page = write_report(b, replay_policy="L").read_text()
    assert not marker.exists()
    assert "Replay: L on Hard, seed 3000000" in page  # the learned episode comes from traces.parquet
    # without traces a learned policy is left out with a note, and asking for it is refused
    (b / "traces.parquet").unlink()
    page = write_report(b).read_text()
    assert not marker.exists() and "without a recorded episode" in page
    with pytest.raises(ValueError, match="replay_policy='L' has no recorded episode"):
        write_report(b, replay_policy="L")


def test_report_replay_equals_a_fresh_episode(bench):
    """The stored trace is the episode itself: PROPOSED's recorded forces equal a re-run's."""
    import gymnasium as gym

    from agents.benchmark.traces import rollout_episode
    from controllers import make_controller

    t = load_result(bench).traces
    rec = t[(t["policy"] == "PROPOSED") & (t["seed"] == SEEDS[0])].reset_index(drop=True)
    env = gym.make("AUVFollow-Hard-v1")
    fresh = rollout_episode(make_controller("PROPOSED", env.unwrapped.task_spec), "AUVFollow-Hard-v1", SEEDS[0])
    assert len(rec) == len(fresh) == 1200
    assert rec["F_u"].to_numpy() == pytest.approx(fresh["F_u"].to_numpy(), rel=1e-6, abs=1e-3)


# --- item 3: no eval ------------------------------------------------------------------------------

def test_policy_kwargs_parsed_without_eval():
    import torch.nn as nn

    from agents.training.zoo_parse import parse_zoo_value

    assert parse_zoo_value("dict(net_arch=dict(pi=[64, 64], vf=[32]), activation_fn=nn.Tanh, log_std_init=-1.0)") \
        == {"net_arch": {"pi": [64, 64], "vf": [32]}, "activation_fn": nn.Tanh, "log_std_init": -1.0}
    assert parse_zoo_value("dict(a=torch.nn.ReLU, b=(1, 2), c={'k': None}, d=True)") == \
        {"a": nn.ReLU, "b": (1, 2), "c": {"k": None}, "d": True}


@pytest.mark.parametrize("text", [
    "dict(a=nn.__builtins__['__import__']('os').system('touch /tmp/x'))",  # the escape
    "dict(a=nn.__builtins__)", "dict(a=__import__('os'))", "dict(a=nn.Module)", "dict(a=(lambda: 1)())",
    "dict(**{'a': 1})", "dict(a=1 + 1)", "dict(a=[x for x in 'ab'])", "dict(a=open)", "dict(a="])
def test_policy_kwargs_escape_attempts_are_refused(text, tmp_path, capsys):
    from agents.training.zoo_parse import parse_zoo_value

    with pytest.raises(ValueError, match="not allowed|keyword arguments only|not a valid expression"):
        parse_zoo_value(text)
    # the CLI: --hp refuses it in one line naming --hp, before anything is created
    with pytest.raises(SystemExit) as e:
        main(["train", "--algo", "ppo", "--mode", "scratch", "--timesteps", "64", "--hp", f"policy_kwargs={text}",
              "--out", str(tmp_path), "--run-name", "r", "--no-progress"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--hp" in err[0] and not (tmp_path / "r").exists()


def test_policy_kwargs_from_a_hyperparameter_yaml_is_not_evaluated(tmp_path):
    from agents.training.config import load_hyperparams

    f = tmp_path / "ppo.yml"
    f.write_text("default:\n  policy_kwargs: \"dict(a=nn.__builtins__['__import__']('os'))\"\n")
    with pytest.raises(ValueError, match="nn.__builtins__"):
        load_hyperparams("ppo", "AUVFollow-S4-v0", f)


# --- item 4: sweep name ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../../x", "a/b", "..", ".", "", "a\\b"])
def test_sweep_name_cannot_leave_storage(name, tmp_path, capsys):
    from agents.benchmark.sweep import SweepConfig

    with pytest.raises(ValueError, match="name="):
        SweepConfig(name=name, storage=str(tmp_path)).validate()
    cfg = tmp_path / "s.yaml"
    cfg.write_text(yaml.safe_dump({"name": name}))
    with pytest.raises(SystemExit) as e:
        main(["sweep", "--config", str(cfg), "--storage", str(tmp_path / "st")])
    assert e.value.code == 2 and "name=" in capsys.readouterr().err
    assert not (tmp_path / "st").exists() and not (tmp_path.parent / "x").exists()


# --- item 5: the cache ---------------------------------------------------------------------------

def test_cache_key_covers_the_benchmark_code_and_package_versions(monkeypatch):
    """stale_cache.sh changes agents/training/obs_stats.py: the key must change with it (and with versions)."""
    def covered(path: str) -> bool:
        return any(path == p or path.startswith(p.rstrip("/") + "/") for p in BE._EPISODE_CODE)

    for path in ("agents/training/obs_stats.py", "agents/training/batched_ppo.py", "agents/benchmark/evaluation.py",
                 "agents/benchmark/policies.py", "agents/benchmark/protocol.py", "controllers/pid.py"):
        assert covered(path), path
    spec = parse_policy("PID")
    k0 = BE._entry_key(spec, None, "AUVFollow-Hard-v1", SEEDS, "code-a")
    assert BE._entry_key(spec, None, "AUVFollow-Hard-v1", SEEDS, "code-b") != k0
    for pkg in ("torch", "stable_baselines3", "casadi", "numpy"):
        v = BE._package_versions()
        monkeypatch.setattr(BE, "_package_versions", lambda v=v, pkg=pkg: {**v, pkg: "0.0-other"})
        assert BE._entry_key(spec, None, "AUVFollow-Hard-v1", SEEDS, "code-a") != k0, pkg
        monkeypatch.undo()


@pytest.mark.parametrize("damage", ["truncated", "nan", "wrong_seeds"])
def test_broken_cache_entry_is_recomputed_not_trusted(damage, tmp_path, monkeypatch):
    monkeypatch.setattr(BE, "_code_fingerprint", lambda: "fixed")
    specs = [parse_policy("PID")]
    fresh = B.evaluate_tier(specs, "S1", [1000, 1001], progress=False, cache_dir=tmp_path)
    (entry,) = tmp_path.glob("*.parquet")
    if damage == "truncated":  # what a Ctrl-C during a non-atomic write left
        entry.write_bytes(entry.read_bytes()[:100])
    else:
        d = pd.read_parquet(entry)
        if damage == "nan":
            d["true_full_mean"] = float("nan")
        else:
            d["seed"] = [5, 6]
        d.to_parquet(entry, index=False)
    with pytest.warns(UserWarning, match="cache entry"):
        again = B.evaluate_tier(specs, "S1", [1000, 1001], progress=False, cache_dir=tmp_path)
    pd.testing.assert_frame_equal(again, fresh)
    assert pd.read_parquet(entry)["seed"].tolist() == [1000, 1001]  # rewritten with the fresh episodes
    assert not list(tmp_path.glob(".*.tmp"))


# --- item 6: no mixed outputs ----------------------------------------------------------------------

def test_interrupted_write_keeps_the_previous_outputs(bench, tmp_path, monkeypatch):
    """p2_partial_write.py: Ctrl-C injected at the PNG of a second run with other policies/seeds."""
    b = _copy(bench, tmp_path / "b")
    before = {f.name: f.read_bytes() for f in b.iterdir()}

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(BO, "plot_leaderboard", boom)
    with pytest.raises(KeyboardInterrupt):
        benchmark(["PID", "PROPOSED"], ["Hard"], seeds=[3000010, 3000011], out_dir=b, n_resamples=50,
                  progress=False)
    assert {f.name: f.read_bytes() for f in b.iterdir()} == before  # nothing new, nothing half-written
    res = load_result(b)
    assert sorted(res.episodes["policy"].unique()) == ["L", "PROPOSED"]


def test_mixed_folder_is_refused(bench, tmp_path, capsys):
    b = _copy(bench, tmp_path / "b")
    other = tmp_path / "other"
    benchmark(["PID"], ["Hard"], seeds=[3000010], out_dir=other, n_resamples=50, progress=False)
    shutil.copy(other / "leaderboard.csv", b / "leaderboard.csv")
    with pytest.raises(ValueError, match="from different benchmark runs"):
        load_result(b)
    with pytest.raises(SystemExit) as e:
        main(["report", "--bench", str(b)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "leaderboard.csv" in err[0]


@pytest.mark.parametrize("name,content", [("benchmark.json", "{not json"), ("leaderboard.csv", "\x00\x01,\n\"a"),
                                          ("episodes.parquet", "PAR1garbage")])
def test_corrupt_file_is_one_line_naming_it(bench, tmp_path, capsys, name, content):
    b = _copy(bench, tmp_path / "b")
    (b / name).write_text(content)
    with pytest.raises(SystemExit) as e:
        main(["report", "--bench", str(b)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and name in err[0]


# --- item 7: the committed leaderboard ------------------------------------------------------------

def test_benchmark_without_out_writes_to_the_ignored_folder(tmp_path, monkeypatch, capsys):
    """default_out_overwrite.sh: a quick look from the repository root (here a scratch copy of its layout)."""
    monkeypatch.chdir(tmp_path)
    assert main(["benchmark", "--tiers", "S1", "--seeds", "1000", "--resamples", "50", "--no-progress",
                 "--policies", "PID"]) == 0
    assert (tmp_path / "results" / "tmp" / "benchmark" / "leaderboard.csv").is_file()
    assert not (tmp_path / "results" / "benchmark").exists()
    assert "results/tmp/benchmark" in capsys.readouterr().err
    assert "/results/tmp/" in (ROOT / ".gitignore").read_text()


# --- item 8: interrupted runs, contradicting statistics ---------------------------------------------

def test_interrupted_run_is_refused(run_copy, tmp_path, capsys):
    """interrupted_run_in_benchmark.sh: seed1 has result.interrupted: true (13,402 of 60,000 steps)."""
    m = tmp_path / "method"
    _copy(run_copy, m / "seed0")
    sig = _copy(run_copy, m / "seed1")
    cfg = yaml.safe_load((sig / "config.yaml").read_text())
    cfg["result"].update({"interrupted": True, "num_timesteps": 13402})
    cfg["run"]["total_timesteps"] = 60000
    (sig / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match=r"seed1 is an interrupted training run .*13402 of 60000"):
        parse_policy(str(m))
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--tiers", "Hard", "--seeds", "3000000-3000001", "--resamples", "50", "--no-progress",
              "--policies", str(m), "--out", str(tmp_path / "bench_m")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "interrupted" in err[-1] and not (tmp_path / "bench_m").exists()
    del cfg["result"]  # still training / killed: no result at all
    (sig / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match="has no 'result'"):
        parse_policy(str(m))


@pytest.mark.parametrize("field,value", [("norm_obs", False), ("clip_obs", 5.0), ("epsilon", 1e-4)])
def test_statistics_contradicting_config_are_refused(run_copy, tmp_path, field, value):
    from agents.training.loading import load_agent

    r = _copy(run_copy, tmp_path / "r")
    stats = json.loads((r / "vecnormalize.json").read_text())
    stats[field] = value
    (r / "vecnormalize.json").write_text(json.dumps(stats))
    with pytest.raises(ValueError, match=rf"vecnormalize.json: {field}=.* contradicts .*config.yaml"):
        load_agent(r)


# --- items 8 and 9: the environment refuses at construction what would fail or blow up later --------

MIXED = {  # p1_mixed.py, p1_mixed_autoreset.py, p1_partial_reset.py
    "jitter_vs_period": (dict(update_period_s=(0.5, 1.0), period_jitter_s=(0.0, 0.9)), "period_jitter_s"),
    "spread_vs_latency_uniform": (dict(latency_model="uniform", latency_s=(0.5, 2.0), latency_spread_s=(0.0, 1.0)),
                                  "latency_spread_s"),
    "speed_min_vs_max": (dict(target_speed_min=(0.0, 1.0), target_speed_max=(0.5, 2.0)), "target_speed_min"),
    "fixed_max_ranged_min": (dict(target_speed_min=(0.0, 1.0), target_speed_max=0.6), "target_speed_min"),
    "fixed_period_ranged_jitter": (dict(update_period_s=0.5, period_jitter_s=(0.0, 0.5)), "period_jitter_s"),
}


@pytest.mark.parametrize("case", sorted(MIXED))
def test_ranges_that_can_draw_an_invalid_condition_are_refused_at_construction(case):
    import gymnasium as gym

    kw, name = MIXED[case]
    with pytest.raises(ValueError, match=name):
        gym.make("AUVFollow-v1", **kw)
    with pytest.raises(ValueError, match=name):
        gym.make_vec("AUVFollow-v1", num_envs=8, **kw)


def test_ranges_whose_every_draw_is_valid_are_accepted_and_never_fail():
    """The boundary: jitter up to just below the shortest period, spread up to the smallest latency."""
    import gymnasium as gym
    import numpy as np

    kw = dict(update_period_s=(1.0, 2.0), period_jitter_s=(0.0, 0.99), latency_model="uniform",
              latency_s=(1.0, 2.0), latency_spread_s=(0.0, 1.0), target_speed_min=(0.0, 0.5),
              target_speed_max=(0.5, 2.0), episode_s=1.0, steady_start_s=0.5)
    v = gym.make_vec("AUVFollow-v1", num_envs=16, **kw)
    v.reset(seed=0)
    for _ in range(200):  # 10 autoresets per env
        v.step(np.zeros((16, 3)))


@pytest.mark.parametrize("scenario", ["S9", "S1"])
def test_scenario_on_a_tier_id_is_refused(scenario):
    import gymnasium as gym

    with pytest.raises(ValueError, match=f"scenario='{scenario}' is invalid on the tier AUVFollow-Hard-v1"):
        gym.make("AUVFollow-Hard-v1", scenario=scenario)


@pytest.mark.parametrize("kw", [dict(force_limits=(3e3, 3e3, 3e3)),  # the issue: |obs| 1e9
                                dict(force_limits=(1e5, 1e5, 1e5), physics_substeps=100)])  # p1_forces2.py
def test_force_limits_the_integrator_cannot_follow_are_refused(kw):
    import gymnasium as gym

    with pytest.raises(ValueError, match="force_limits=.*yaw rate can reach F_r / N_r"):
        gym.make("AUVFollow-v1", max_distance_m=1e4, **kw)


def test_accepted_large_force_limits_stay_finite():
    """RK4 on the surge/sway block (eigenvalues -d +- i r, |r| <= F_r / N_r): with the check
    passed, random bang-bang actions keep every observation finite (p1_forces2.py's search)."""
    import gymnasium as gym
    import numpy as np

    env = gym.make("AUVFollow-v1", force_limits=(3e3, 3e3, 3e3), physics_substeps=10, max_distance_m=1e4)
    rng = np.random.default_rng(1)
    for ep in range(5):
        env.reset(seed=ep)
        for _ in range(1200):
            obs, r, term, trunc, _ = env.step(np.sign(rng.uniform(-1, 1, 3)))
            assert np.isfinite(obs).all() and np.isfinite(r)
            if term or trunc:
                break


# --- item 11: a user's controller on the leaderboard ----------------------------------------------

def test_user_controller_class_goes_on_the_leaderboard(tmp_path, capsys):
    """The documented 20-line example, by module:Class, scores the same as evaluating it directly."""
    import inspect

    import gymnasium as gym

    from controllers.evaluation import evaluate
    from examples.user_controller import GoToReference

    assert len(inspect.getsource(GoToReference).splitlines()) <= 20  # the controller itself, without its demo main
    spec = parse_policy("mine=examples.user_controller:GoToReference")
    assert (spec.label, spec.kind, spec.controller) == ("mine", "external", "examples.user_controller:GoToReference")
    res = benchmark(["PID", "mine=examples.user_controller:GoToReference"], ["S1"], seeds=[1000, 1001],
                    n_resamples=50, progress=False, out_dir=tmp_path / "b")
    row = res.leaderboard.set_index("policy").loc["mine"]
    env = gym.make("AUVFollow-S1-v0")
    direct = evaluate(GoToReference(env.unwrapped.task_spec), "AUVFollow-S1-v0", [1000, 1001], progress=False)
    assert row["kind"] == "external" and res.leaderboard.set_index("policy").loc["PID", "best_classical"] == "PID"
    assert row["true_steady_mean_mean"] == pytest.approx(direct["true_steady_mean"].mean(), rel=1e-9)
    assert not direct["terminated"].any()
    # the CLI, from the repository root, and the report of that folder (which never imports it)
    assert main(["benchmark", "--tiers", "S1", "--seeds", "1000", "--resamples", "50", "--no-progress",
                 "--policies", "examples.user_controller:GoToReference", "--out", str(tmp_path / "c")]) == 0
    assert "GoToReference" in (tmp_path / "c" / "leaderboard.md").read_text()


@pytest.mark.parametrize("text,needle", [("nosuchmodule_xyz:Cls", "cannot be imported"),
                                         ("examples.user_controller:Nope", "has no class 'Nope'")])
def test_user_controller_errors_name_the_policy(text, needle, capsys, tmp_path):
    with pytest.raises(ValueError, match=needle):
        parse_policy(text)
    with pytest.raises(SystemExit) as e:
        main(["benchmark", "--tiers", "S1", "--seeds", "1000", "--no-progress", "--policies", text,
              "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and text in err[0]


# --- items 10, 12, 13, 17: messages, seeds, help, files ---------------------------------------------

def test_refusals_are_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    def no_work(*a, **k):
        raise AssertionError("work started before the refusal")

    monkeypatch.setattr(BR, "evaluate_tier", no_work)
    a_file = tmp_path / "f.txt"
    a_file.write_text("x")
    cases = [(["benchmark", "--tiers", "S1", "--policies", "PID", "--out", str(a_file)], "--out"),
             (["benchmark", "--tiers", "S1", "--policies", "PID", "--bootstrap-seed", "-1"], "--bootstrap-seed"),
             (["report", "--bench", str(tmp_path), "--out", str(tmp_path)], "--out"),
             (["report", "--bench", str(tmp_path / "none")], "episodes.parquet")]
    for argv, needle in cases:
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and needle in err[-1], (argv, err)
        assert not err[-1].startswith("Traceback")


def test_ctrl_c_in_benchmark_and_report_is_one_line_exit_130(capsys, monkeypatch, tmp_path):
    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(BR, "evaluate_tier", interrupt)
    argv = ["benchmark", "--tiers", "S1", "--policies", "PID", "--no-progress", "--out", str(tmp_path / "b")]
    assert main(argv) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == \
        "auv-follow benchmark: interrupted (nothing half-written was kept)"
    import agents.benchmark.report

    monkeypatch.setattr(agents.benchmark.report, "load_result", interrupt)
    assert main(["report", "--bench", str(tmp_path)]) == 130


def test_sweep_failures_exit_1_in_one_line(capsys, monkeypatch):
    import agents.benchmark.sweep as S

    def all_failed(cfg):
        raise S.SweepFailed("all 2 trial(s) of sweep 'x' failed; the last lines of the first error: boom")

    monkeypatch.setattr(S, "sweep", all_failed)
    with pytest.raises(SystemExit) as e:
        main(["sweep", "--name", "x"])
    assert e.value.code == 1 and capsys.readouterr().err.strip().splitlines() == [
        "auv-follow sweep: error: all 2 trial(s) of sweep 'x' failed; the last lines of the first error: boom"]
    df = pd.DataFrame({"val_true_steady_mean_iqm": [1.0]})
    df.attrs["errors"] = 1
    monkeypatch.setattr(S, "sweep", lambda cfg: df)
    with pytest.raises(SystemExit) as e:
        main(["sweep", "--name", "x"])
    assert e.value.code == 1 and "1 trial(s) failed" in capsys.readouterr().err


def test_config_error_survives_pickling_across_ray():
    """A trial's ConfigError is re-raised as a ValueError; that one pickles (Ray ships errors)."""
    exc = ValueError("trial ppo/S4/seed 0: hyperparameter x is invalid")
    assert str(pickle.loads(pickle.dumps(exc))) == str(exc)
    import inspect

    import agents.benchmark.sweep as S

    assert "except ConfigError" in inspect.getsource(S.run_trial)


def test_default_seeds_are_the_families_test_seeds():
    from auv_follow_env.tiers import TIERS

    assert B.default_test_seeds("AUVFollow-Hard-v1") == list(range(3_000_000, 3_000_010))
    assert B.default_test_seeds("AUVFollow-Hard-v1") == list(TIERS["Hard"].test_seeds[:10])
    assert B.default_test_seeds("AUVFollow-S4-v0") == list(range(1000, 1010))
    assert B.default_test_seeds("AUVFollow-v1") == list(range(1000, 1010))


def test_compare_of_a_v1_agent_uses_its_env_and_its_test_seeds(run_copy, tmp_path, capsys):
    assert main(["compare", str(run_copy), "--controllers", "PID", "--seeds", "3000000", "--no-progress",
                 "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "AUVFollow-Hard-v1" in out


def test_training_on_the_ood_tier_warns(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["train", "--algo", "ppo", "--env", "AUVFollow-Extreme-v1", "--mode", "scratch", "--run-name", "a/b",
              "--out", str(tmp_path)])
    assert "out-of-distribution testing only" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["train", "evaluate", "compare", "benchmark", "report", "sweep"])
def test_help_has_descriptions_and_no_true_defaults_of_flags(cmd, capsys):
    with pytest.raises(SystemExit):
        main([cmd, "--help"])
    text = capsys.readouterr().out
    assert "default: True" not in text and "default: False" not in text
    if cmd in ("benchmark", "report", "sweep"):
        assert "(default:" in text and len(text.split("options:")[0].splitlines()) > 3


def test_expected_files():
    import tomllib

    assert "MIT License" in (ROOT / "LICENSE").read_text()
    assert tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"] == "MIT"
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT" and cff["references"][0]["year"] == 2026
    log = (ROOT / "CHANGELOG.md").read_text()
    assert "1e-9 relative" in log and "v1 ids" in log
    readme = (ROOT / "README.md").read_text()
    assert "pip install" in readme and "Python >= 3.10" in readme and "AUV_FOLLOW_INSTALL_BROWSER" in readme


# --- item 15: the tier claims are measured -------------------------------------------------------------

def test_extreme_overlaps_hard_where_the_tables_say():
    """By hand from auv_follow_env/tiers.py: Extreme's target_speed U[0.45, 0.65] overlaps Hard's
    U[0.4, 0.6]; its update_period_s U[4, 6] shares the end 4 with Hard's U[2, 4]."""
    from experiments.tier_claims import overlaps

    found = {line.split(":")[0]: line for line in overlaps()}
    assert "(overlap)" in found["target_speed"] and "(they share an end value)" in found["update_period_s"]
    assert "burst_p_bad_good" not in found  # Hard U[0.3, 0.5], Extreme 0.25: outside


def test_xss_report_runs_no_script_in_a_browser(bench, tmp_path):
    """xss_kind_tier.sh + p3_browser.py: the page with the injected kind/tier/label, in headless
    Chromium: no alert() call, no injected <img> or javascript: link (skipped without a browser)."""
    from tests.test_report import CHROMEDRIVER, _ensure_browser

    browser = _ensure_browser()
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed: pip install -e .[dev]")
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    b = _copy(bench, tmp_path / "b")
    _unseal(b)
    p = b / "leaderboard.csv"
    lines = p.read_text().splitlines()
    head = lines[0].split(",")
    row = lines[1].split(",")
    row[head.index("kind")] = f'"{XSS}"'
    row[head.index("policy")] = '"<a href=""javascript:alert(2)"">click</a>"'
    lines[1] = ",".join(row)
    row2 = list(row)
    row2[head.index("tier")] = "\"<img src=x onerror=alert('tier')>\""
    lines.append(",".join(row2))
    p.write_text("\n".join(lines) + "\n")
    page = write_report(b)
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--user-data-dir={tmp_path / 'profile'}"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {
            "source": "window.__alerts=[];window.alert=function(m){window.__alerts.push(String(m));};"})
        driver.set_page_load_timeout(120)
        driver.get(page.resolve().as_uri())
        from selenium.webdriver.support.ui import WebDriverWait

        # (the checks below would pass on a page not yet built: wait for its table first)
        WebDriverWait(driver, 60).until(lambda d: d.find_elements(By.CSS_SELECTOR, "table.leaderboard td"))
        assert driver.execute_script("return window.__alerts") == []
        assert driver.find_elements(By.CSS_SELECTOR, "img") == []
        assert driver.find_elements(By.CSS_SELECTOR, "a[href^='javascript']") == []
        cells = [c.text for c in driver.find_elements(By.CSS_SELECTOR, "table.leaderboard td")]
        assert XSS in cells  # shown as text
    finally:
        driver.quit()
