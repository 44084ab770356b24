"""agents.benchmark.sweep: a CPU-only 2-trial Ray Tune sweep of a few thousand steps completes, and after
an (injected) crash of a trial the same call resumes it from its checkpoint."""

from __future__ import annotations

import pytest

pytest.importorskip("ray.tune", reason="ray[tune] is not installed: pip install -e .[sweep]")

from agents.benchmark.sweep import SweepConfig, sweep  # noqa: E402
from agents.training.loading import load_agent  # noqa: E402


def test_two_trial_sweep_completes_and_resumes_after_a_crash(tmp_path, monkeypatch):
    import ray

    monkeypatch.delenv("RAY_ADDRESS", raising=False)  # a local instance of its own, whatever the host runs

    marker = tmp_path / "fail_once"
    marker.touch()
    cfg = SweepConfig(grid={"algo": ["ppo"], "mode": ["scratch"], "tier": ["S1"], "seed": [0, 1],
                            "hp.n_steps": [256], "hp.batch_size": [256], "hp.n_epochs": [1]},
                      timesteps=2048, chunks=2, n_envs=2, validation_seeds=[900], storage=str(tmp_path / "sweeps"),
                      name="t", fail_once_marker=str(marker), verbose=0)
    try:
        first = sweep(cfg)
        assert not marker.exists()  # one trial crashed after its first checkpoint
        assert len(first) == 2 and (first["chunk"] == 0).any()
        ray.shutdown()  # a fresh driver, as after Ctrl-C
        again = sweep(cfg)
    finally:
        ray.shutdown()
    assert len(again) == 2
    assert (again["chunk"] == 1).all() and (again["timesteps"] == 2048).all()
    # the crashed trial continued from chunk 0's checkpoint instead of starting over
    assert (again["resumed_from_chunk"] == 0).sum() == 1
    assert again["val_true_steady_mean_iqm"].notna().all()
    assert (tmp_path / "sweeps" / "t" / "trials.csv").is_file()
    agent = load_agent(again["run_dir"].iloc[0])  # the best trial feeds `auv-follow benchmark`
    assert agent.env_id == "AUVFollow-S1-v0"


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match=r"grid\['algo'\] has 'dqn'"):
        SweepConfig(grid={"algo": ["dqn"]}).validate()
    with pytest.raises(ValueError, match=r"chunks=0"):
        SweepConfig(chunks=0).validate()
    with pytest.raises(ValueError, match=r"overlap the published test seeds"):
        SweepConfig(validation_seeds=[1000]).validate()
