"""Hardening IV: each test names the reproducer in ../shared/reproducers/hardening4/ whose
input it is built on. The recovery rule for non-finite observations (E16, item 3) is in
test_nonfinite_obs.py; SIGTERM and SIGHUP to training in test_agents_hardening.py."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import auv_follow_env  # noqa: F401
from agents.cli import main
from controllers import EstimatorConfig

ROOT = Path(__file__).resolve().parent.parent
RUNS = ROOT / "results" / "benchmark" / "runs"
BPPO_RUN = RUNS / "bppo5-LeaderHard-scratch-priv-rate-heading-s0"
LE_RUN = RUNS / "le1-LeaderHard-s0"
SB3_RUN = RUNS / "ppo-scratch" / "ppo-Hard-scratch-seed0"


def _cli(argv, capsys):
    """(exit code, stderr lines) of ``auv-follow <argv>`` in-process."""
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr().err.strip().splitlines()


def _copy(run: Path, tmp_path: Path) -> Path:
    d = tmp_path / run.name
    shutil.copytree(run, d)
    return d


def _edit_config(run: Path, edit) -> None:
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    edit(cfg)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))


# --- E1 leader_modes_range.py, E2 leader_cross_ranges.py -------------------------------------------

def test_a_range_of_leader_modes_is_refused():
    with pytest.raises(ValueError, match=r"leader_modes=\(0\.0, 2\.0\) is invalid: .*fixed per env"):
        gym.make("AUVFollow-Leader-Hard-v1", leader_modes=(0.0, 2.0))


@pytest.mark.parametrize(("env_id", "kw", "names"), [
    ("AUVFollow-Leader-Easy-v1", {"target_speed_max": (0.5, 2.0), "leader_cruise_speed": (0.4, 1.5)},
     ("target_speed_max", "leader_cruise_speed")),
    ("AUVFollow-Leader-Hard-v1", {"target_yaw_rate_max": (0.3, 0.5)}, ("target_yaw_rate_max", "leader_uturn_rate")),
    ("AUVFollow-Leader-Hard-v1", {"target_speed_max": (0.95, 2.0)}, ("target_speed_max", "leader_sprint_speed")),
])
def test_leader_rules_hold_for_every_draw_not_only_the_range_ends(env_id, kw, names):
    """leader_cross_ranges.py: a draw inside the ranges (speed cap 0.6 m/s, cruise 1.2 m/s) broke the
    rule although both range ends kept it. The rule must hold for the worst pair: the cap's low end
    against the commanded value's high end."""
    with pytest.raises(ValueError) as e:
        gym.make(env_id, **kw)
    for n in names:
        assert n in str(e.value)


def test_ranges_that_keep_the_rule_for_every_draw_are_accepted():
    env = gym.make("AUVFollow-Leader-Easy-v1", target_speed_max=(1.6, 2.0), leader_cruise_speed=(0.4, 1.5))
    for s in range(20):
        c = env.reset(seed=s)[1]["condition"]
        assert c["target_speed_max"] >= c["leader_cruise_speed"]


# --- E9 estimator_config_breaks.py, E10 estimator_config_numpy.py ----------------------------------

@pytest.mark.parametrize(("field", "value"), [
    ("pf_temper", 0.0), ("pf_temper", 1e308), ("limm_sojourn", 1e308), ("q_acc", 1e308), ("tau_u", -1.0),
    ("pf_particles", 0), ("limm_shape", 9), ("sigma_pos", float("nan")), ("imm_q_panels", 0), ("imm_q_panels", 65),
    ("imm_q_panels", 2.5)])
def test_estimator_settings_outside_their_bounds_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=rf"{field}=.* is invalid"):
        EstimatorConfig(**{field: value})


def test_estimator_settings_take_numpy_scalars_as_python_numbers():
    c = EstimatorConfig(pf_temper=np.float32(0.5), pf_particles=np.int64(200), q_acc=np.float64(0.01))
    assert c.pf_temper == 0.5 and type(c.pf_temper) is float
    assert c.pf_particles == 200 and type(c.pf_particles) is int
    with pytest.raises(ValueError, match=r"pf_particles=2.5 is invalid: must be a whole number"):
        EstimatorConfig(pf_particles=2.5)


# --- E3 evaluate_estimator_run.py, E4 out_file_exists.py -------------------------------------------

def test_evaluate_a_learned_estimator_run_and_overwrite_its_out_file(tmp_path, capsys):
    """evaluate_estimator_run.py (AttributeError env_wrapper) and out_file_exists.py (an existing --out
    file was refused as "not a directory"): twice into the same file, the second replaces the first."""
    out = tmp_path / "e.csv"
    out.write_text("old\n")
    for _ in range(2):
        code, err = _cli(["evaluate", str(LE_RUN), "--seeds", "7000000", "--no-progress", "--out", str(out)], capsys)
        assert code in (0, None), err
    text = out.read_text()
    assert "old" not in text and text.count("7000000") == 1


# --- E5 report_huge_file.sh: size limits on the files a user gives ---------------------------------

def test_a_huge_file_is_refused_by_name_before_it_is_read(tmp_path, capsys):
    from auv_follow_env._files import LIMITS, check_size

    big = tmp_path / "leaderboard.csv"
    with open(big, "wb") as f:  # sparse: free on disk
        f.truncate(LIMITS["table"] + 1)
    with pytest.raises(ValueError, match=r"leaderboard.csv is 256 MB: larger than the 256 MB"):
        check_size(big, "table")
    small = tmp_path / "small.csv"
    small.write_bytes(b"x" * 10)
    assert check_size(small, "table") == small
    # a run directory whose config.yaml is sparse-huge: the reader refuses it in one line
    run = _copy(BPPO_RUN, tmp_path)
    with open(run / "config.yaml", "r+b") as f:
        f.truncate(LIMITS["text"] + 1)
    code, err = _cli(["evaluate", str(run), "--seeds", "7000000", "--no-progress"], capsys)
    assert code == 2 and len(err) == 1 and "config.yaml is 16 MB: larger than the 16 MB" in err[0], err


def test_report_refuses_a_huge_leaderboard(tmp_path, capsys):
    bench = tmp_path / "bench"
    code, err = _cli(["benchmark", "--tiers", "Hard", "--seeds", "3000000-3000001", "--resamples", "50",
                      "--no-progress", "--policies", "PID", "--out", str(bench)], capsys)
    assert code in (0, None), err
    (bench / "leaderboard.csv").unlink()
    with open(bench / "leaderboard.csv", "wb") as f:
        f.truncate(2 << 30)
    code, err = _cli(["report", "--bench", str(bench), "--out", str(tmp_path / "r.html")], capsys)
    assert code == 2 and len(err) == 1 and "leaderboard.csv is 2,048 MB" in err[0], err
    assert not (tmp_path / "r.html").exists()


# --- E7 resume_yaw_from.py --------------------------------------------------------------------------

def _train(out: Path, name: str, *extra: str, timesteps: int = 1024) -> list[str]:
    return ["train", "--algo", "bppo", "--env", "AUVFollow-Easy-v1", "--mode", "scratch", "--n-envs", "8",
            "--timesteps", str(timesteps), "--eval-freq", "0", "--no-final-eval", "--no-progress",
            "--no-tensorboard", "--out", str(out), "--run-name", name, "--hp", "n_steps=64", *extra]


def test_resume_refuses_settings_that_change_the_policy_or_its_task(tmp_path, capsys):
    """resume_yaw_from.py: a yaw_from=PROPOSED_KF_DOB checkpoint resumed without it, so the policy's
    unused yaw output drove the heading. Every setting of the policy's interface, its reward and its
    task is compared; the same settings resume."""
    out = tmp_path / "runs"
    code, err = _cli(_train(out, "yaw", "--checkpoint-freq", "512", "--hp", "yaw_from=PROPOSED_KF_DOB",
                            "--hp", "heading_coef=0.5"), capsys)
    assert code in (0, None), err
    ck = str(out / "yaw" / "checkpoints" / "model_512_steps.zip")
    same = ["--checkpoint-freq", "0", "--resume", ck, "--hp", "yaw_from=PROPOSED_KF_DOB", "--hp", "heading_coef=0.5"]
    for extra, needle in [
        (["--checkpoint-freq", "0", "--resume", ck, "--hp", "heading_coef=0.5"],
         "yaw_from='PROPOSED_KF_DOB' (now None)"),
        ([*same[:-2], "--hp", "heading_coef=0.2"], "heading_coef=0.5 (now 0.2)"),
        ([*same, "--obs", "raw"], "observation='estimator' (now 'raw')"),
    ]:
        code, err = _cli(_train(out, "again", *extra, timesteps=2048), capsys)
        assert code == 2 and len(err) == 1 and "argument --resume" in err[0] and needle in err[0], (extra, err)
        assert not (out / "again").exists()  # refused before anything was written
    code, err = _cli(_train(out, "again", *same, timesteps=2048), capsys)
    assert code in (0, None), err
    assert yaml.safe_load((out / "again" / "config.yaml").read_text())["observation"]["yaw_from"] == "PROPOSED_KF_DOB"


def test_resume_refuses_another_env(tmp_path, capsys):
    out = tmp_path / "runs"
    assert _cli(_train(out, "a", "--checkpoint-freq", "0"), capsys)[0] in (0, None)
    argv = _train(out, "b", "--checkpoint-freq", "0", "--resume", str(out / "a" / "model.zip"), timesteps=2048)
    argv[argv.index("AUVFollow-Easy-v1")] = "AUVFollow-Medium-v1"
    code, err = _cli(argv, capsys)
    assert code == 2 and "env_id='AUVFollow-Easy-v1'" in err[0] and "'AUVFollow-Medium-v1'" in err[0], err


# --- E8 sweep_resume_settings.sh --------------------------------------------------------------------

def test_a_sweep_is_not_resumed_with_other_settings(tmp_path):
    """sweep_resume_settings.sh: a second sweep with --timesteps 4096 printed the first one's results
    (2048). The comparison runs before Ray starts."""
    from agents.benchmark.sweep import SweepConfig, _check_same_settings, _write_settings

    exp = tmp_path / "e8"
    exp.mkdir()
    _write_settings(SweepConfig(name="e8", timesteps=2048, chunks=1), exp)
    _check_same_settings(SweepConfig(name="e8", timesteps=2048, chunks=1, verbose=0, address="ray://x:1"), exp)
    with pytest.raises(ValueError, match=r"timesteps: 2048 then, 4096 now.*--no-resume"):
        _check_same_settings(SweepConfig(name="e8", timesteps=4096, chunks=1), exp)
    with pytest.raises(ValueError, match=r"grid: "):
        _check_same_settings(SweepConfig(name="e8", timesteps=2048, chunks=1, grid={"seed": [0]}), exp)
    (exp / "sweep.yaml").unlink()
    with pytest.raises(ValueError, match="has no sweep.yaml"):
        _check_same_settings(SweepConfig(name="e8", timesteps=2048, chunks=1), exp)


# --- E11 run_env_id_import.py -----------------------------------------------------------------------

@pytest.mark.parametrize("run", [BPPO_RUN, LE_RUN, SB3_RUN])
def test_a_run_env_id_that_names_a_module_is_refused_before_any_import(run, tmp_path, capsys):
    d = _copy(run, tmp_path)

    def edit(cfg):
        cfg["run"]["env_id"] = "this:AUVFollow-Leader-Hard-v1"
    _edit_config(d, edit)
    sys.modules.pop("this", None)
    code, err = _cli(["evaluate", str(d), "--seeds", "7000000", "--no-progress"], capsys)
    assert code == 2 and len(err) == 1 and "run.env_id='this:AUVFollow-Leader-Hard-v1' is unknown" in err[0], err
    assert "this" not in sys.modules


# --- E12 model_garbage_message.py -------------------------------------------------------------------

@pytest.mark.parametrize("run", [BPPO_RUN, LE_RUN])
@pytest.mark.parametrize("garbage", ["bytes", "zip"])
def test_a_garbage_model_file_is_one_line_without_unpickling_advice(run, garbage, tmp_path, capsys):
    d = _copy(run, tmp_path)
    if garbage == "bytes":
        (d / "model.zip").write_bytes(os.urandom(4000))
    else:  # a zip whose pickle holds an object (torch's weights_only refuses it)
        with zipfile.ZipFile(d / "model.zip", "w") as z:
            z.writestr("archive/data.pkl", b"\x80\x02cos\nsystem\nq\x00.")
    code, err = _cli(["evaluate", str(d), "--seeds", "7000000", "--no-progress"], capsys)
    assert code == 2 and len(err) == 1, err
    assert "model.zip is not a" in err[0] and "weights_only" not in err[0]


# --- E13 sb3_envkw_traceback.py, E14 sb3_normalize_missing.py ---------------------------------------

def test_an_sb3_run_with_bad_env_kwargs_is_one_line(tmp_path, capsys):
    d = _copy(SB3_RUN, tmp_path)

    def edit(cfg):
        cfg["run"]["env_kwargs"] = {"loss_prob": float("nan")}
    _edit_config(d, edit)
    code, err = _cli(["evaluate", str(d), "--seeds", "3000000", "--no-progress"], capsys)
    assert code == 2 and len(err) == 1 and "env_kwargs={'loss_prob': nan} are refused" in err[0], err


def test_statistics_without_a_normalize_section_are_refused(tmp_path, capsys):
    """sb3_normalize_missing.py: the run scored 3.89 m on raw observations instead of 1.25 m."""
    d = _copy(SB3_RUN, tmp_path)
    _edit_config(d, lambda cfg: cfg.pop("normalize"))
    code, err = _cli(["evaluate", str(d), "--seeds", "3000000", "--no-progress"], capsys)
    assert code == 2 and len(err) == 1 and "records no normalize section" in err[0], err


# --- E15 bench_tier_twice.py ------------------------------------------------------------------------

@pytest.mark.parametrize("tiers", [["Leader-Hard", "Leader-Hard"], ["Hard", "AUVFollow-Hard-v1"]])
def test_a_tier_given_twice_is_refused_up_front(tiers, tmp_path, capsys):
    import agents.benchmark.run as run

    code, err = _cli(["benchmark", "--tiers", *tiers, "--seeds", "7000000-7000001", "--no-progress",
                      "--policies", "PID", "--out", str(tmp_path / "b")], capsys)
    assert code == 2 and len(err) == 1 and err[0].startswith("auv-follow benchmark: error: argument --tiers:"), err
    assert "twice" in err[0]
    with pytest.raises(ValueError, match="twice"):
        run.benchmark(["PID"], tiers, seeds=[7000000])


# --- item 2: SIGTERM and SIGHUP to a benchmark keep the previous result set --------------------------

@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_a_stop_signal_to_a_benchmark_keeps_the_previous_set(sig, code, tmp_path, capsys):
    out = tmp_path / "b"
    assert _cli(["benchmark", "--tiers", "Hard", "--seeds", "3000000-3000001", "--resamples", "50", "--no-progress",
                 "--policies", "PID", "--out", str(out)], capsys)[0] in (0, None)
    before = {f.name: f.read_bytes() for f in out.iterdir()}

    def defaults():
        for s in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(s, signal.SIG_DFL)
    argv = ["benchmark", "--tiers", "Hard", "Medium", "--seeds", "3000000-3000029", "--resamples", "50",
            "--policies", "MPC", "PROPOSED", "--out", str(out)]
    proc = subprocess.Popen([sys.executable, "-m", "agents.cli", *argv], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=defaults,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    time.sleep(12)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    name = signal.Signals(sig).name
    assert f"auv-follow benchmark: interrupted by {name} (nothing half-written was kept)" in err
    assert "Traceback" not in err
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before


# --- item 2: every settings class given numpy scalars and extreme values -----------------------------

def _settings_cases():
    from controllers import Gains, PIDGains
    from controllers.mpc import CasadiMPCConfig, MPCConfig

    return [(Gains, "K_p"), (Gains, "derivative_tc"), (PIDGains, "K_P"), (PIDGains, "derivative_tc"),
            (MPCConfig, "horizon_s"), (MPCConfig, "w_pos"), (MPCConfig, "intervals"), (MPCConfig, "admm_iterations"),
            (CasadiMPCConfig, "horizon_s"), (CasadiMPCConfig, "sqp_iterations")]


@pytest.mark.parametrize(("cls", "field"), _settings_cases(), ids=lambda x: getattr(x, "__name__", x))
def test_controller_settings_take_numpy_scalars_and_refuse_extremes_by_name(cls, field):
    """MPCConfig refused np.float32(3.0) and accepted horizon_s=1e308 and intervals=10**30 (a huge QP);
    Gains let numpy raise its own TypeError for a string or 10**30."""
    default = getattr(cls(), field)
    np_value = np.int64(default) if isinstance(default, int) else np.float32(default)
    c = cls(**{field: np_value})
    assert getattr(c, field) == default
    bad = [-1, float("nan"), float("inf"), "x", True]
    if cls.__name__ in ("MPCConfig", "CasadiMPCConfig"):
        bad += [10**30, 1e308]  # bounded: horizon <= 600 s, <= 1000 intervals, weights <= 1e6
    for v in bad:
        with pytest.raises(ValueError, match=rf"{field}=.* is invalid"):
            cls(**{field: v})


def test_training_and_sweep_settings_take_numpy_scalars_and_refuse_extremes_by_name():
    """TrainConfig refused max_minutes=np.float32(1.0) and accepted total_timesteps=10**30; SweepConfig
    refused np.int64 counts and accepted cpus_per_trial=inf and max_failures=-1."""
    from agents.benchmark.sweep import SweepConfig
    from agents.training.config import TrainConfig

    TrainConfig(max_minutes=np.float32(1.0), total_timesteps=np.int64(4096)).validate()
    for field, v in [("total_timesteps", 10**30), ("max_minutes", 1e308), ("max_minutes", np.bool_(True))]:
        with pytest.raises(ValueError, match=rf"{field}=.* is invalid"):
            TrainConfig(**{field: v}).validate()
    cfg = SweepConfig(timesteps=np.int64(4096), chunks=np.int64(2), num_samples=np.int64(1),
                      cpus_per_trial=np.float32(1.0))
    cfg.validate()
    assert type(cfg.timesteps) is int and type(cfg.cpus_per_trial) is float  # (written to sweep.yaml as such)
    for field, v in [("cpus_per_trial", float("inf")), ("max_failures", -1), ("timesteps", 10**30)]:
        with pytest.raises(ValueError, match=rf"{field}=.* is invalid"):
            SweepConfig(**{field: v}).validate()


def test_the_disturbance_observer_takes_numpy_scalars():
    """It refused time_constant=np.float32(0.5) as "not a finite number"."""
    from controllers import DisturbanceObserver

    spec = gym.make("AUVFollow-Hard-v1").unwrapped.task_spec
    obs = DisturbanceObserver(spec.nominal, np.float64(spec.dt), spec.force_limits, np.float32(0.5))
    assert obs.time_constant == 0.5
    for name, kw in [("time_constant", {"time_constant": float("nan")}), ("thruster_tc_s", {"thruster_tc_s": -1.0}),
                     ("time_constant", {"time_constant": "x"})]:
        with pytest.raises(ValueError, match=rf"{name}=.* is invalid"):
            DisturbanceObserver(spec.nominal, spec.dt, spec.force_limits, **kw)
