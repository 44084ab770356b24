"""RecurrentPPO (sb3-contrib) through agents.train: a tiny run trains, reloads, and as a
policy keeps its LSTM state itself, so batched and single-env evaluation agree."""

from __future__ import annotations

import numpy as np

from agents.training.config import TrainConfig
from agents.training.loading import load_agent
from agents.training.runner import train
from controllers.evaluation import evaluate, evaluate_batched


def test_recurrent_ppo_trains_and_evaluates_batched_like_single(tmp_path):
    run = train(TrainConfig(algo="recurrentppo", mode="scratch", env_id="AUVFollow-S4-v0", total_timesteps=1024,
                            n_envs=2, hyperparams={"n_steps": 256, "batch_size": 256, "n_epochs": 1},
                            out_dir=str(tmp_path), checkpoint_freq=0, eval_freq=0, progress_bar=False,
                            tensorboard=False))
    agent = load_agent(run)
    assert agent.recurrent and agent.name == "RECURRENTPPO (scratch)"
    batched = evaluate_batched([agent], "AUVFollow-S4-v0", [1000, 1001], progress=False)
    agent.reset()
    single = evaluate(agent, "AUVFollow-S4-v0", [1000, 1001], progress=False)
    np.testing.assert_allclose(batched["true_steady_mean"], single["true_steady_mean"], rtol=1e-9)
    # the state is carried: a fresh call differs from continuing the same episode
    obs = np.zeros((1, 16), dtype=np.float32)
    agent.reset()
    a0, _ = agent.predict(obs, episode_start=np.array([True]))
    a1, _ = agent.predict(obs, episode_start=np.array([False]))
    a2, _ = agent.predict(obs, episode_start=np.array([True]))
    np.testing.assert_array_equal(a0, a2)
    assert not np.array_equal(a0, a1)
