"""Agents: residual wrapper contract, tiny training runs of PPO/SAC/TD3 (save, reload, same
actions), resume, the CLI end to end, and clear errors for bad arguments."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import yaml

import auv_follow_env  # noqa: F401
from agents.cli import main
from agents.training.config import TrainConfig, load_hyperparams
from agents.training.history import residual_obs_dim
from agents.training.loading import load_agent
from agents.training.residual import ResidualWrapper, make_residual_wrapper
from agents.training.runner import train
from controllers import make_controller

ENV = "AUVFollow-S4-v0"
_TINY = {"checkpoint_freq": 0, "eval_freq": 0, "progress_bar": False, "tensorboard": False, "final_eval": False}


def _tiny_ppo(tmp_path, **kw) -> TrainConfig:
    base = dict(algo="ppo", total_timesteps=2048, n_envs=2, hyperparams={"n_steps": 256, "batch_size": 128,
                                                                          "n_epochs": 2},
                out_dir=str(tmp_path), **_TINY)
    base.update(kw)
    return TrainConfig(**base)


# --- residual wrapper -----------------------------------------------------------------------

@pytest.mark.parametrize("controller", ["PROPOSED", "PID"])
def test_zero_residual_reproduces_base_controller_bit_for_bit(controller):
    ref_env = gym.make(ENV)
    base = make_controller(controller, ref_env.unwrapped.task_spec)
    obs, _ = ref_env.reset(seed=3)
    ref_obs, ref_err, start = [obs], [], True
    while True:
        a, _ = base.predict(obs, episode_start=np.array([start]))
        start = False
        obs, _, term, trunc, info = ref_env.step(a)
        ref_obs.append(obs)
        ref_err.append(info["tracking_error"])
        if term or trunc:
            ref_metrics = info["episode_metrics"]
            break

    env = ResidualWrapper(gym.make(ENV), controller=controller)
    wobs, _ = env.reset(seed=3)
    got_obs, got_err = [wobs[:16]], []
    zero = np.zeros(3, dtype=np.float32)
    while True:
        wobs, _, term, trunc, info = env.step(zero)
        got_obs.append(wobs[:16])
        got_err.append(info["tracking_error"])
        if term or trunc:
            break
    assert len(got_err) == len(ref_err) == 1200
    np.testing.assert_array_equal(np.asarray(got_obs), np.asarray(ref_obs))
    np.testing.assert_array_equal(np.asarray(got_err), np.asarray(ref_err))
    assert info["episode_metrics"] == ref_metrics


def test_residual_observation_and_action():
    env = ResidualWrapper(gym.make(ENV), scale=0.2, history_len=3, history_stride=5)
    assert env.observation_space.shape == (residual_obs_dim(True, 3),) == (28,)
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == (28,)
    np.testing.assert_array_equal(obs[16:19], info["base_action"])
    np.testing.assert_array_equal(obs[19:], 0.0)  # no history yet
    for _ in range(40):
        base = info["base_action"].astype(np.float64)
        obs, _, _, _, info = env.step(np.ones(3, dtype=np.float32))
        np.testing.assert_array_equal(info["applied_action"], np.clip(base + 0.2, -1, 1))
    assert np.any(obs[19:] != 0.0)
    env2 = ResidualWrapper(gym.make(ENV), include_base_action=False, history_len=0)
    assert env2.observation_space.shape == (16,)


def test_residual_wrapper_errors():
    with pytest.raises(ValueError, match="controller='LQR'.*PROPOSED"):
        ResidualWrapper(gym.make(ENV), controller="LQR")
    with pytest.raises(ValueError, match="scale"):
        make_residual_wrapper(scale=0.0)
    with pytest.raises(ValueError, match="history_stride"):
        make_residual_wrapper(history_stride=0)


# --- training, saving, reloading ---------------------------------------------------------------

def _probe_obs(agent, n=16):
    env = agent.env_wrapper(gym.make(agent.env_id)) if agent.env_wrapper else gym.make(agent.env_id)
    obs, _ = env.reset(seed=11)
    out = [obs]
    for _ in range(n - 1):
        obs, *_ = env.step(env.action_space.sample())
        out.append(obs)
    return np.asarray(out)


@pytest.mark.parametrize("algo,mode", [("ppo", "residual"), ("sac", "scratch"), ("td3", "residual")])
def test_train_save_load_same_actions(tmp_path, algo, mode):
    if algo == "ppo":
        cfg = _tiny_ppo(tmp_path, mode=mode, progress_bar=True)
    else:
        cfg = TrainConfig(algo=algo, mode=mode, total_timesteps=300, n_envs=1, out_dir=str(tmp_path),
                          hyperparams={"learning_starts": 100, "batch_size": 64, "train_freq": 4,
                                       "gradient_steps": 1}, **_TINY)
    run, model = train(cfg, return_model=True)
    assert (run / "model.zip").is_file() and (run / "vecnormalize.pkl").is_file()
    assert (run / "vecnormalize.json").is_file()
    conf = yaml.safe_load((run / "config.yaml").read_text())
    assert conf["run"]["algo"] == algo and conf["result"]["num_timesteps"] >= cfg.total_timesteps
    assert {"python", "torch", "stable_baselines3", "gymnasium", "numpy", "git_commit"} <= set(conf["versions"])
    agent = load_agent(run)
    obs = _probe_obs(agent)
    norm = model.get_env().normalize_obs(obs)
    expected, _ = model.predict(norm, deterministic=True)
    got, _ = agent.predict(obs)
    np.testing.assert_array_equal(got, expected)
    single, _ = agent.predict(obs[0])
    np.testing.assert_allclose(single, expected[0], rtol=1e-5, atol=1e-6)  # batch-1 BLAS rounding


def test_residual_policy_on_raw_env_matches_wrapper(tmp_path):
    from controllers.evaluation import evaluate

    agent = load_agent(train(_tiny_ppo(tmp_path, total_timesteps=512, hyperparams={"n_steps": 256})))
    wrapped = evaluate(agent, ENV, [1000, 1001], env_wrapper=agent.env_wrapper, progress=False)
    raw = evaluate(agent.raw_policy(), ENV, [1000, 1001], progress=False)
    cols = ["return", "true_steady_mean", "true_full_rmse", "true_full_max"]
    np.testing.assert_array_equal(raw[cols].to_numpy(), wrapped[cols].to_numpy())
    obs = np.zeros((3, 16), dtype=np.float32)
    assert agent.raw_policy().predict(obs, episode_start=np.ones(3, bool))[0].shape == (3, 3)


def test_resume_continues_step_count(tmp_path):
    run = train(_tiny_ppo(tmp_path, total_timesteps=1024, checkpoint_freq=512, run_name="first"))
    ckpt = run / "checkpoints" / "model_512_steps.zip"
    assert ckpt.is_file() and (run / "checkpoints" / "model_vecnormalize_512_steps.pkl").is_file()
    assert (run / "checkpoints" / "model_vecnormalize_512_steps.json").is_file()
    run2, model = train(_tiny_ppo(tmp_path, total_timesteps=2048, resume_from=str(ckpt), run_name="second"),
                        return_model=True)
    res = yaml.safe_load((run2 / "config.yaml").read_text())["result"]
    assert res["start_timesteps"] == 512
    assert model.num_timesteps == res["num_timesteps"] >= 2048
    assert load_agent(ckpt).env_id == ENV  # a checkpoint loads with its run's config


def test_hyperparams_yaml():
    hp = load_hyperparams("ppo", ENV)
    assert hp["policy"] == "MlpPolicy" and isinstance(hp["policy_kwargs"], dict)
    assert float(hp["n_timesteps"]) > 0
    for algo in ("sac", "td3"):
        assert load_hyperparams(algo, "AUVFollow-S1-v0")["gamma"] > 0  # default section


# --- CLI ---------------------------------------------------------------------------------------

def test_cli_end_to_end(tmp_path, capsys):
    main(["train", "--algo", "ppo", "--mode", "residual", "--timesteps", "512", "--n-envs", "2",
          "--hp", "n_steps=256", "--hp", "batch_size=128", "--eval-freq", "512", "--eval-episodes", "1",
          "--checkpoint-freq", "0", "--no-progress", "--no-tensorboard", "--out", str(tmp_path),
          "--run-name", "cli", "--seed", "4", "--env-kwarg", "disturbance=L1"])
    run = tmp_path / "cli"
    assert (run / "model.zip").is_file() and (run / "eval" / "evaluations.npz").is_file()
    conf = yaml.safe_load((run / "config.yaml").read_text())
    assert conf["run"]["env_kwargs"] == {"disturbance": "L1"}
    # the final score: eval_episodes=1 episode from eval_seed (990,000 by default), printed and recorded
    assert conf["result"]["interrupted"] is False and conf["result"]["final_score"]["seeds"] == [990000]
    out = capsys.readouterr().out
    assert "final score on AUVFollow-S4-v0, seeds 990000-990000" in out
    assert f"{conf['result']['final_score']['true_steady_mean_m']:.4f} m" in out
    csv = tmp_path / "eval.csv"
    main(["evaluate", str(run), "--seeds", "1000", "--out", str(csv), "--no-progress"])
    assert csv.is_file()
    main(["compare", str(run), "--seeds", "1000,1001", "--controllers", "PROPOSED", "PID",
          "--out", str(tmp_path / "cmp"), "--no-progress"])
    for f in ("compare.csv", "compare_summary.csv", "compare.md", "compare.png"):
        assert (tmp_path / "cmp" / f).is_file()
    out = capsys.readouterr().out
    assert "| PROPOSED |" in out and f"in {tmp_path / 'cmp'}/" in out  # the table, and where it wrote
    import pandas as pd

    df = pd.read_csv(tmp_path / "cmp" / "compare.csv")
    assert len(df) == 6 and df.loc[df.policy.str.contains("residual"), "own_steady_mean"].isna().all()
    assert df.loc[df.policy == "PROPOSED", "own_steady_mean"].notna().all()


@pytest.mark.parametrize("argv,needle", [
    (["train", "--algo", "a2c"], "--algo"),
    (["train", "--env", "CartPole-v1"], "--env"),
    (["train", "--controller", "LQR"], "--controller"),
    (["train", "--timesteps", "0"], "--timesteps"),
    (["train", "--timesteps", "-5"], "--timesteps"),
    (["train", "--max-minutes", "0"], "--max-minutes"),
    (["evaluate", "does/not/exist"], "does not exist"),
    (["compare", "does/not/exist.zip", "--seeds", "1"], "does not exist"),
])
def test_cli_errors(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert needle in capsys.readouterr().err


def test_library_errors(tmp_path):
    with pytest.raises(ValueError, match="algo='a2c'.*ppo"):
        TrainConfig(algo="a2c").validate()
    with pytest.raises(ValueError, match="env_id='Nope-v0'"):
        TrainConfig(env_id="Nope-v0").validate()
    with pytest.raises(ValueError, match="controller='LQR'"):
        TrainConfig(controller="LQR").validate()
    with pytest.raises(ValueError, match="total_timesteps"):
        TrainConfig(total_timesteps=0).validate()
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_agent(tmp_path / "missing.zip")
    with pytest.raises(ValueError, match="resume_from=.*missing.zip.*no such model file"):
        TrainConfig(resume_from=str(tmp_path / "missing.zip")).validate()


# --- scripts ------------------------------------------------------------------------------------

def test_train_benchmark_script_tiny(tmp_path):
    from experiments import train_benchmark

    train_benchmark.main(["--stage", "all", "--minutes", "0.01", "--max-timesteps", "4096", "--test-seeds", "1000",
                          "--out", str(tmp_path), "--no-progress"])
    for f in ("benchmark.md", "benchmark.csv", "benchmark.png", "learning_curves.png"):
        assert (tmp_path / f).is_file()
    text = (tmp_path / "benchmark.md").read_text()
    assert "PROPOSED" in text and "(residual)" in text and "(scratch)" in text


def test_bench_ppo_script_tiny(tmp_path):
    from experiments import bench_ppo

    out = bench_ppo.main(["--timesteps", "256", "--n-envs", "1", "--repeats", "1", "--out", str(tmp_path / "b.md")])
    assert (tmp_path / "b.md").is_file() and out["rows"][0][1] > 0
