"""NativeVecEnv: the batched env behind SB3's VecEnv API, against SB3's own make_vec_env."""

from __future__ import annotations

import numpy as np
import pytest

from agents.training.vec_adapter import NativeVecEnv

SHORT = {"episode_s": 1.0, "steady_start_s": 0.5}  # 20 steps per episode


def _reference_venv(n, seed):
    from stable_baselines3.common.env_util import make_vec_env

    return make_vec_env("AUVFollow-S2-v0", n_envs=n, seed=seed, env_kwargs=SHORT)


def test_matches_sb3_make_vec_env_across_resets():
    n, seed = 3, 7
    ours = NativeVecEnv("AUVFollow-S2-v0", n, seed=seed, env_kwargs=SHORT)
    ref = _reference_venv(n, seed)
    o1, o2 = ours.reset(), ref.reset()
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(50):  # 2.5 episodes: SB3's immediate autoreset on both sides
        a = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        o1, r1, d1, i1 = ours.step(a)
        o2, r2, d2, i2 = ref.step(a)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_allclose(r1, r2, rtol=0, atol=1e-6)  # float32 rewards on both sides
        np.testing.assert_array_equal(d1, d2)
        for a_, b_ in zip(i1, i2, strict=True):
            if "terminal_observation" in b_:
                ended += 1
                np.testing.assert_array_equal(a_["terminal_observation"], b_["terminal_observation"])
                assert a_["TimeLimit.truncated"] == b_.get("TimeLimit.truncated", False)
                assert a_["episode"]["l"] == b_["episode"]["l"] == 20
                assert a_["episode"]["r"] == pytest.approx(b_["episode"]["r"], abs=1e-4)
    assert ended == 2 * n
    ours.close()
    ref.close()


def test_ppo_learns_on_it_for_a_few_steps():
    from stable_baselines3 import PPO

    venv = NativeVecEnv("AUVFollow-S1-v0", 4, seed=0, env_kwargs=SHORT)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(256)
    assert model.num_timesteps == 256
    venv.close()


def test_bad_arguments():
    with pytest.raises(ValueError, match="env_id"):
        NativeVecEnv("CartPole-v1", 2)
    with pytest.raises(ValueError, match="num_envs"):
        NativeVecEnv("AUVFollow-S1-v0", 0)


def test_cli_trains_on_the_native_vector_env(tmp_path, capsys):
    from agents.cli import main

    main(["train", "--algo", "ppo", "--mode", "scratch", "--vec", "native", "--env", "AUVFollow-S1-v0",
          "--timesteps", "512", "--n-envs", "4", "--hp", "n_steps=64", "--hp", "batch_size=64",
          "--checkpoint-freq", "0", "--eval-freq", "0", "--out", str(tmp_path), "--run-name", "nat",
          "--no-progress", "--no-tensorboard"])
    assert (tmp_path / "nat" / "model.zip").is_file()
    with pytest.raises(SystemExit):
        main(["train", "--algo", "ppo", "--mode", "residual", "--vec", "native", "--timesteps", "64",
              "--out", str(tmp_path)])
    assert "vec='native' trains from scratch only" in capsys.readouterr().err
