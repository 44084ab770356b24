"""Hardening III, the training entry points (``auv-follow train``, agents/training/,
agents/training/batched_ppo.py): every setting checked before any work, a diverged or failed run never
recorded as finished, writes that fail leave nothing half-written. Each test names the
reproducer in ../shared/reproducers/hardening3/ whose input it is built on."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from agents.cli import main

EASY = "AUVFollow-Easy-v1"


def _train_args(out: Path, name: str, *extra: str, algo: str = "bppo", n_envs: int = 8,
                timesteps: int = 64) -> list[str]:
    return ["train", "--algo", algo, "--env", EASY, "--mode", "scratch", "--n-envs", str(n_envs),
            "--timesteps", str(timesteps), "--eval-freq", "0", "--checkpoint-freq", "0", "--no-final-eval",
            "--no-progress", "--no-tensorboard", "--out", str(out), "--run-name", name, *extra]


def _hp(*pairs: str) -> list[str]:
    return [x for p in pairs for x in ("--hp", p)]


def _refused(capsys, argv: list[str]) -> str:
    """Run the CLI, expect a one-line refusal (exit code 2, no exception); return that line."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2, err
    assert len(err) == 1 and err[0].startswith("auv-follow train: error: argument"), err
    return err[0]


# --- D6 normalize_values.py: the values inside normalize=dict(...) ---------------------------------

@pytest.mark.parametrize("algo, value, named", [
    ("ppo", "dict(norm_obs=True, norm_reward=False, clip_obs=-1.0)", "clip_obs=-1.0"),  # the reproducer's SB3 case
    ("bppo", "dict(clip_obs=0)", "clip_obs=0"),
    ("bppo", "{clip_obs: .nan}", "clip_obs=nan"),
    ("ppo", "dict(epsilon=0.0)", "epsilon=0.0"),
    ("bppo", "dict(gamma=1.5)", "gamma=1.5"),
    ("ppo", "dict(clip_reward='big')", "clip_reward='big'"),
    ("bppo", "dict(norm_obs=1)", "norm_obs=1"),
    ("bppo", "dict(norm_obs=True, clip=5)", "['clip']"),
])
def test_normalize_values_are_refused_before_work(tmp_path, capsys, algo, value, named):
    """normalize_values.py: SB3 trained with clip_obs=-1 and the run could not be loaded; now
    every value is checked (bools; finite numbers > 0; gamma in (0, 1]) before anything is made."""
    out = tmp_path / "runs"
    line = _refused(capsys, _train_args(out, "r", *_hp(f"normalize={value}", "n_steps=64", "batch_size=64"),
                                        algo=algo, n_envs=1 if algo == "ppo" else 8))
    assert "--hp" in line and named in line and ("must be" in line or "valid keys" in line)
    assert not out.exists()


def test_bppo_honours_clip_obs_and_epsilon(tmp_path):
    """normalize_values.py: bppo trained with clip_obs=5.0 always clipped at 10 and wrote 10 into the
    statistics, so evaluate refused the finished run; now the run clips at 5 and loads."""
    from agents.training.loading import evaluate_agent, load_agent

    out = tmp_path / "runs"
    assert main(_train_args(out, "b", *_hp("normalize=dict(norm_obs=True, clip_obs=5.0, epsilon=1.0e-6)"))) == 0
    stats = json.loads((out / "b" / "vecnormalize.json").read_text())
    assert (stats["clip_obs"], stats["epsilon"]) == (5.0, 1e-6)
    agent = load_agent(out / "b")
    # an observation far from the mean is clipped at the asked bound, not at 10
    far = agent.stats.mean + 1e6 * np.sqrt(agent.stats.var + 1e-6)
    assert np.abs(agent.stats.normalize(far[None, :])).max() == pytest.approx(5.0)
    assert np.isfinite(evaluate_agent(agent, [500], progress=False)["true_steady_mean"]).all()
    # without the settings, SB3's defaults as before
    assert main(_train_args(out, "d")) == 0
    stats = json.loads((out / "d" / "vecnormalize.json").read_text())
    assert (stats["clip_obs"], stats["epsilon"]) == (10.0, 1e-8)


def test_bppo_training_clips_observations_at_the_asked_bound(tmp_path, monkeypatch):
    """normalize_values.py: the observations the network trains on are clipped at clip_obs."""
    import agents.training.batched_ppo as bp

    seen = []
    real = bp._update

    def spy(net, opt, hp, obs, *args, **kw):
        seen.append(float(np.abs(obs).max()))
        return real(net, opt, hp, obs, *args, **kw)

    monkeypatch.setattr(bp, "_update", spy)
    # the z-scores of each varying feature have mean square 1 over the samples behind the statistics
    # (the first step's 8 envs): some |z| >= 1, so clipped at 10 the maximum would exceed 0.5
    assert main(_train_args(tmp_path, "c", *_hp("normalize=dict(clip_obs=0.5)"))) == 0
    assert seen and max(seen) <= 0.5 + 1e-7


# --- D7 bppo_nan_run.py: NaN training is refused up front or stopped ---------------------------------

@pytest.mark.parametrize("hp, named", [
    ("policy_kwargs=dict(log_std_init=1e999)", "log_std_init=inf"),  # the reproducer's input
    ("policy_kwargs=dict(log_std_init=1000.0)", "log_std_init=1000.0"),
    ("learning_rate=1e6", "learning_rate=1000000.0"),
    ("learning_rate=1.5", "learning_rate=1.5"),
])
def test_nan_prone_settings_are_refused(tmp_path, capsys, hp, named):
    """bppo_nan_run.py: log_std_init=1e999 / 1000 or learning_rate=1e6 trained to NaN and the run was
    recorded as finished; now they are outside the checked ranges (log_std_init in [-20, 2], bppo
    [-5, 2]; learning_rate in (0, 1])."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(hp)))
    assert named in line and "is invalid: must be" in line
    assert not (tmp_path / "runs").exists()


def _nan_actor(monkeypatch):
    """Make every new bppo network act NaN (its mean layer's bias), as a diverged one does."""
    import torch

    import agents.training.batched_ppo as bp

    real = bp._build_net

    def build(obs_dim, pk):
        net = real(obs_dim, pk)
        with torch.no_grad():
            net.actor[-1].bias.fill_(float("nan"))
        return net

    monkeypatch.setattr(bp, "_build_net", build)


def test_nan_actions_stop_training_and_the_run_is_not_finished(tmp_path, capsys, monkeypatch):
    """bppo_nan_run.py: a run whose policy turned NaN was recorded as finished (interrupted: false, a
    model.zip of NaN weights). Now training stops at the first non-finite action with one line
    (exit code 1), config.yaml records result.failed, no model.zip is written and load_agent says why."""
    from agents.training.loading import load_agent

    _nan_actor(monkeypatch)
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        main(_train_args(out, "r"))
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 1
    assert err[-1].startswith("auv-follow train: error: training failed at 0 steps") and "not finite" in err[-1]
    res = yaml.safe_load((out / "r" / "config.yaml").read_text())["result"]
    assert res["interrupted"] is False and "diverged" in res["failed"] and "actions" in res["failed"]
    assert not (out / "r" / "model.zip").exists()
    with pytest.raises(FileNotFoundError, match="training failed .*diverged"):
        load_agent(out / "r")


def test_nan_parameters_after_an_update_stop_training(tmp_path, monkeypatch):
    """bppo_nan_run.py (learning_rate=1e6: the first update made the weights NaN): the parameters are
    checked after every update; the checkpoint before the failure is kept."""
    import torch

    import agents.training.batched_ppo as bp
    from agents.training.config import TrainConfig, TrainingFailed
    from agents.training.runner import train

    real = bp._update
    calls = []

    def update(net, *args, **kw):
        out = real(net, *args, **kw)
        calls.append(1)
        if len(calls) == 2:
            with torch.no_grad():
                net.critic[0].weight[0, 0] = float("inf")
        return out

    monkeypatch.setattr(bp, "_update", update)
    cfg = TrainConfig(algo="bppo", env_id=EASY, mode="scratch", n_envs=8, total_timesteps=1024, eval_freq=0,
                      checkpoint_freq=256, final_eval=False, progress_bar=False, tensorboard=False,
                      out_dir=str(tmp_path), run_name="r")
    with pytest.raises(TrainingFailed, match=r"critic\.0\.weight is not finite .* at 512 steps") as e:
        train(cfg)
    assert e.value.num_timesteps == 512
    run = tmp_path / "r"
    assert "critic.0.weight" in yaml.safe_load((run / "config.yaml").read_text())["result"]["failed"]
    assert not (run / "model.zip").exists()
    assert sorted(p.name for p in (run / "checkpoints").glob("*.zip")) == ["model_256_steps.zip"]
    assert not list(run.rglob("*.tmp"))


def test_sb3_nan_training_stops_with_one_line(tmp_path, capsys, monkeypatch):
    """bppo_nan_run.py for SB3's PPO: NaN weights raised torch's distribution check as a raw
    traceback after the run directory was made; now one line, result.failed, no model.zip."""
    import torch
    from stable_baselines3 import PPO

    real = PPO.train

    def train(self):
        real(self)
        with torch.no_grad():
            for p in self.policy.parameters():
                p.fill_(float("nan"))

    monkeypatch.setattr(PPO, "train", train)
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        main(_train_args(out, "s", *_hp("n_steps=64", "batch_size=64"), algo="ppo", n_envs=1, timesteps=256))
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 1 and err[-1].startswith("auv-follow train: error: training failed at 64 steps")
    assert "diverged" in err[-1]
    res = yaml.safe_load((out / "s" / "config.yaml").read_text())["result"]
    assert res["failed"].startswith("training diverged") and not (out / "s" / "model.zip").exists()


# --- D8 bppo_teacher_ignored.py ----------------------------------------------------------------------

@pytest.mark.parametrize("hps, named", [
    (["teacher=PID"], "teacher='PID' needs distill_steps > 0"),  # the reproducer's input
    (["teacher_link=real"], "teacher_link='real' needs a teacher"),
])
def test_a_teacher_that_would_never_be_asked_is_refused(tmp_path, capsys, hps, named):
    """bppo_teacher_ignored.py: teacher=PID without distill_steps trained by PPO only while
    config.yaml recorded the teacher; now refused before any work."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(*hps)))
    assert named in line
    assert not (tmp_path / "runs").exists()


# --- D9 bppo_resume_nostats.py, D13 (resume with other policy_kwargs) -----------------------------------

@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    """A bppo run of 256 steps (8 envs x 32 steps: one update) with a checkpoint at 256."""
    out = tmp_path_factory.mktemp("bppo_base")
    assert main(["train", "--algo", "bppo", "--env", EASY, "--mode", "scratch", "--n-envs", "8", "--timesteps", "256",
                 "--checkpoint-freq", "256", "--eval-freq", "0", "--no-final-eval", "--no-progress",
                 "--no-tensorboard", "--out", str(out), "--run-name", "a"]) == 0
    return out / "a"


def test_resume_without_statistics_is_refused(base_run, tmp_path, capsys):
    """bppo_resume_nostats.py: a checkpoint whose statistics JSON is missing resumed with the
    observation statistics restarted from zero; now refused, naming the missing file."""
    import shutil

    ck = tmp_path / "a" / "checkpoints"
    shutil.copytree(base_run, tmp_path / "a")
    (ck / "model_vecnormalize_256_steps.json").unlink()
    out = tmp_path / "runs"
    line = _refused(capsys, _train_args(out, "b", "--resume", str(ck / "model_256_steps.zip"), timesteps=512))
    assert "--resume" in line and "model_vecnormalize_256_steps.json is missing" in line
    assert not out.exists()


def test_resume_continues_the_statistics(base_run, tmp_path):
    """bppo_resume_nostats.py, the right way: with the statistics the resumed run's count goes on
    from the checkpoint's: 1e-4 (the initial count) + 8 envs x 64 steps = 512 samples at 512 steps."""
    ck = base_run / "checkpoints" / "model_256_steps.zip"
    assert main(_train_args(tmp_path, "b", "--resume", str(ck), timesteps=512)) == 0
    count = json.loads((tmp_path / "b" / "vecnormalize.json").read_text())["count"]
    assert count == pytest.approx(512 + 1e-4, abs=1e-9)


def test_resume_with_other_policy_kwargs_is_refused(base_run, tmp_path, capsys):
    """bppo_tracebacks.py: --resume with policy_kwargs net_arch=[32] raised a ValueError after the
    run directory was made; now one line naming both settings, and no directory."""
    out = tmp_path / "runs"
    line = _refused(capsys, _train_args(out, "res", "--resume", str(base_run / "model.zip"),
                                        *_hp("policy_kwargs=dict(net_arch=[32])"), timesteps=2048))
    assert "--resume" in line and "'net_arch': [64, 64]" in line and "'net_arch': [32]" in line
    assert not out.exists()


# --- D10 bppo_net_arch_dict.py -----------------------------------------------------------------------

def _weights(state_dict, prefix):
    return [tuple(v.shape) for k, v in state_dict.items() if k.startswith(prefix) and k.endswith("weight")]


def test_net_arch_dict_builds_separate_actor_and_critic(tmp_path):
    """bppo_net_arch_dict.py: dict(pi=[8], vf=[256, 256]) built an [8] critic; now the actor has
    [8] and the critic [256, 256] (the observation is D wide, 3 actions, 1 value), and the run
    loads and acts."""
    import torch

    from agents.training.loading import load_agent

    assert main(_train_args(tmp_path, "r", *_hp("policy_kwargs=dict(net_arch=dict(pi=[8], vf=[256, 256]))"))) == 0
    data = torch.load(tmp_path / "r" / "model.zip", weights_only=True)
    d = int(data["obs_dim"])
    assert _weights(data["state_dict"], "actor") == [(8, d), (3, 8)]
    assert _weights(data["state_dict"], "critic") == [(256, d), (256, 256), (1, 256)]
    agent = load_agent(tmp_path / "r")
    action, _ = agent.predict(np.zeros(agent.builder.obs_width))
    assert action.shape == (3,) and np.isfinite(action).all()


@pytest.mark.parametrize("arch, named", [
    ("dict(qf=[8])", "['qf'] that bppo does not read"),  # SAC's key: gave [64, 64] silently
    ("dict(pi=[8])", "exactly the keys 'pi' (actor) and 'vf' (critic)"),
    ("dict(pi=[8], vf=[0])", "net_arch={'pi': [8], 'vf': [0]} is invalid"),
])
def test_net_arch_dicts_that_cannot_be_honoured_are_refused(tmp_path, capsys, arch, named):
    """bppo_net_arch_dict.py: a dict without both pi and vf is refused, not replaced by defaults."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(f"policy_kwargs=dict(net_arch={arch})")))
    assert named in line
    assert not (tmp_path / "runs").exists()


# --- D13 bppo_tracebacks.py --------------------------------------------------------------------------

@pytest.mark.parametrize("hp, named", [
    ("policy_kwargs={log_std_init: .nan}", "log_std_init=nan"),
    ("policy_kwargs=dict(log_std_init='big')", "log_std_init='big'"),
    ("policy_kwargs=dict(net_arch=[True, True])", "net_arch=[True, True]"),
    ("policy_kwargs=dict(net_arch=[1000000000])", "net_arch=[1000000000]"),
    ("policy_kwargs=dict(net_arch=[8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8, 8])", "at most 16"),
    ("policy_kwargs=dict(gru_size=True)", "gru_size=True"),
    ("policy_kwargs=dict(log_std_init=-10.0)", "log_std_init=-10.0"),
    ("n_steps=1000000000", "n_steps=1000000000"),
    ("random_phase=1", "random_phase=1"),
    ("torch_threads=true", "torch_threads=True"),
    ("learning_rate=" + "9" * 400, "learning_rate=999"),
    ("n_steps=" + "9" * 400, "n_steps=999"),
])
def test_bppo_values_are_refused_in_one_line_before_the_run_directory(tmp_path, capsys, hp, named):
    """bppo_tracebacks.py: .nan, a string, bools as ints, n_steps=1e9 (MemoryError), a huge
    net_arch gave tracebacks after the run directory was made; numbers beyond float's range gave
    OverflowError. Now one line naming the value, and no directory."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(hp)))
    assert "--hp" in line and named in line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("hp", ["n_steps=null", "learning_rate=null", "normalize=null", "lr_schedule=null",
                                "teacher_link=null", "distill_steps=null", "torch_threads=null",
                                "policy_kwargs={log_std_init: null}", "policy_kwargs={gru_size: null}",
                                "policy_kwargs={net_arch: null}", "gae_lambda=null", "random_phase=null"])
def test_none_hyperparameters_are_refused_in_one_line(tmp_path, capsys, hp):
    """bppo_tracebacks.py, the same class: a hyperparameter given as null (None) where the
    algorithm needs a value is refused by name (target_kl=null and teacher=null mean "off")."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(hp)))
    assert hp.split("=")[0] in line and "None" in line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("algo, arch, named", [
    ("ppo", "[True, True]", "net_arch=[True, True]"),  # nn.Linear(n, True) built a 1-unit layer
    ("ppo", "dict(pi=[8], qf=[8])", "['qf'] that ppo does not read"),  # SB3's PPO ignored qf without a word
    ("sac", "dict(pi=[8], vf=[8])", "['vf'] that sac does not read"),
    ("td3", "[64, 1000000000]", "net_arch=[64, 1000000000]"),
])
def test_sb3_net_arch_is_checked_like_bppo(algo, arch, named, tmp_path, capsys):
    """bppo_net_arch_dict.py / bppo_tracebacks.py for the SB3 algorithms: bools as sizes, dict keys
    the algorithm does not read and huge layers are refused before work."""
    line = _refused(capsys, _train_args(tmp_path / "runs", "r", *_hp(f"policy_kwargs=dict(net_arch={arch})"),
                                        algo=algo, n_envs=1))
    assert named in line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("field, value", [("out_dir", None), ("progress_bar", None), ("tensorboard", "no"),
                                          ("final_eval", 1), ("include_base_action", None), ("scale", None),
                                          ("history_stride", 0)])
def test_train_config_fields_of_the_wrong_type_are_refused(tmp_path, field, value):
    """The same class in the library API: a None or a string where TrainConfig needs a path, a
    bool or a number is a ConfigError naming the field (out_dir=None was a TypeError from pathlib;
    scale=None in scratch mode a TypeError from bppo's observation builder)."""
    from agents.training.config import ConfigError, TrainConfig
    from agents.training.runner import train

    kw = {"algo": "bppo", "env_id": EASY, "mode": "scratch", "out_dir": str(tmp_path / "runs"), "n_envs": 8,
          "total_timesteps": 64, "eval_freq": 0, "checkpoint_freq": 0, "final_eval": False, "progress_bar": False,
          "tensorboard": False, field: value}
    with pytest.raises(ConfigError, match=rf"^{field}=") as e:
        train(TrainConfig(**kw))
    assert e.value.field == field and not (tmp_path / "runs").exists()


# --- D16 write_errors.sh (the train part) --------------------------------------------------------------

@pytest.fixture
def read_only_dir(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield ro
    finally:
        subprocess.run(["umount", str(ro)], check=False)


@pytest.mark.parametrize("algo", ["bppo", "ppo"])
def test_train_out_on_a_read_only_file_system_is_refused_before_work(read_only_dir, capsys, algo):
    """write_errors.sh: `train --out` on a read-only file system failed with a traceback once the
    run directory was made (after the trial env and model); now one line before any work."""
    line = _refused(capsys, _train_args(read_only_dir / "runs", "r", algo=algo, n_envs=1))
    assert "--out" in line and "not writable" in line


def test_train_out_under_a_file_is_refused(tmp_path, capsys):
    """write_errors.sh, the same class: --out below a regular file (mkdir: NotADirectoryError)."""
    (tmp_path / "f").write_text("x")
    line = _refused(capsys, _train_args(tmp_path / "f" / "runs", "r"))
    assert "--out" in line and "is not a directory" in line


def test_train_library_refuses_a_read_only_out_dir(tmp_path, monkeypatch):
    """write_errors.sh for the library API: TrainConfig.validate checks out_dir's writability
    (os.access says no, as on a read-only mount) before anything is built."""
    import agents.train as tr

    real = os.access
    monkeypatch.setattr(os, "access", lambda p, m: False if Path(p) == tmp_path else real(p, m))
    cfg = tr.TrainConfig(algo="bppo", env_id=EASY, mode="scratch", out_dir=str(tmp_path / "runs"))
    with pytest.raises(tr.ConfigError, match="cannot be written.*not writable") as e:
        tr.train(cfg)
    assert e.value.field == "out_dir" and not (tmp_path / "runs").exists()


def test_a_failed_model_write_leaves_no_temporary_file(tmp_path, capsys, monkeypatch):
    """write_errors.sh: bppo left ``model.zip.tmp`` when the final save failed (disk full); now
    the temporary file is removed, the run records result.failed and the CLI prints one line."""
    import torch

    real = torch.save

    def full_disk(obj, f, *a, **kw):
        if str(f).endswith("model.zip.tmp"):
            Path(f).write_bytes(b"partial")
            raise OSError(28, "No space left on device")
        return real(obj, f, *a, **kw)

    monkeypatch.setattr(torch, "save", full_disk)
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        main(_train_args(out, "r"))
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 1 and "No space left on device" in err[-1] and "Traceback" not in "".join(err)
    assert not list(out.rglob("*.tmp")) and not (out / "r" / "model.zip").exists()
    assert "a write failed" in yaml.safe_load((out / "r" / "config.yaml").read_text())["result"]["failed"]


def test_statistics_and_config_writes_leave_no_temporary_file(tmp_path, monkeypatch):
    """write_errors.sh: write_obs_stats and the config.yaml writer keep the old file and remove
    their temporary file when the write fails."""
    from agents.training.obs_stats import ObsStats, write_obs_stats
    from agents.training.rundir import _write_yaml

    stats = ObsStats(norm_obs=True, mean=np.zeros(2), var=np.ones(2), count=1.0, clip_obs=10.0, epsilon=1e-8)
    (tmp_path / "s.json").write_text("old")
    (tmp_path / "c.yaml").write_text("old")

    def fail(self, target):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "replace", fail)
    with pytest.raises(OSError):
        write_obs_stats(stats, tmp_path / "s.json")
    with pytest.raises(OSError):
        _write_yaml(tmp_path / "c.yaml", {"a": 1})
    assert (tmp_path / "s.json").read_text() == "old" and (tmp_path / "c.yaml").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "s.json"]


# --- D22 bppo_whole_float.py ---------------------------------------------------------------------------

INTEGER_KEYS = ["n_steps", "batch_size", "n_epochs", "torch_threads", "n_eval_seeds", "obs_norm_window",
                "distill_steps"]


@pytest.mark.parametrize("key", INTEGER_KEYS)
def test_one_rule_for_integer_hyperparameters(key):
    """bppo_whole_float.py: distill_steps=1.0e+6 was refused as "must be a whole number" while
    n_steps=32.0 was accepted. Now every integer key takes a whole float (converted to int) or
    YAML's string 1e6 for 10**6 and refuses 32.5 and bools, with the same message."""
    from agents.training.config import ConfigError, check_hyperparams

    whole = 4.0 if key == "torch_threads" else 32.0
    assert check_hyperparams("bppo", {key: whole})[key] == int(whole)
    assert type(check_hyperparams("bppo", {key: whole})[key]) is int
    if key not in ("torch_threads", "n_eval_seeds"):
        assert check_hyperparams("bppo", {key: "1e6"})[key] == 1_000_000
    for bad in (32.5, True, "many", math.inf):
        with pytest.raises(ConfigError, match=rf"hyperparameter {key}=.* is invalid: must be a whole number"):
            check_hyperparams("bppo", {key: bad})


def test_whole_float_distill_steps_trains(tmp_path):
    """bppo_whole_float.py's input: teacher=PID, distill_steps=1.0e+6 is accepted (and recorded as
    the integer 1000000)."""
    assert main(_train_args(tmp_path, "a", *_hp("teacher=PID", "distill_steps=1.0e+6"))) == 0
    cfg = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    assert cfg["hyperparams"]["distill_steps"] == 1_000_000
    with open(tmp_path / "a" / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(math.isnan(float(r["entropy"])) for r in rows)  # imitation updates only


def test_policy_kwargs_sizes_follow_the_same_rule():
    """bppo_whole_float.py, the same class inside policy_kwargs: net_arch [64.0] and gru_size 32.0
    are whole numbers; 8.5 is not."""
    from agents.training.batched_ppo import _policy_kwargs

    pk = _policy_kwargs({"net_arch": [64.0, 32], "gru_size": 32.0})
    assert pk["net_arch"] == [64, 32] and pk["gru_size"] == 32 and type(pk["gru_size"]) is int
    with pytest.raises(ValueError, match=r"net_arch=\[8.5\] is invalid"):
        _policy_kwargs({"net_arch": [8.5]})


def test_the_committed_runs_still_load():
    """Stricter checks of policy_kwargs must not refuse a committed bppo model: each one's stored
    policy_kwargs passes and builds the same network."""
    import torch

    from agents.training.batched_ppo import _build_net, _policy_kwargs

    root = Path(__file__).resolve().parent.parent / "results"
    models = sorted(root.glob("*/runs/**/model.zip"))
    checked = 0
    for m in models:
        cfg = yaml.safe_load((m.parent / "config.yaml").read_text())
        if cfg["run"]["algo"] != "bppo":
            continue
        data = torch.load(m, weights_only=True)
        net = _build_net(int(data["obs_dim"]), _policy_kwargs(data["policy_kwargs"]))
        net.load_state_dict(data["state_dict"])
        checked += 1
    if not checked:
        pytest.skip("no committed bppo runs")
