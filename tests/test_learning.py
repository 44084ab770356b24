"""What the batched trainer promises a learner: normalisers that forget (closed forms), the
evaluated policy equal to the training-time actor, a progress count equal to the steps
collected, learning-curve seeds held out from training, an episode-error log that is filled,
and the fast path as the command line's default."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
import yaml

EASY = "AUVFollow-Easy-v1"


def _tiny_bppo(tmp_path, *extra: str, name: str = "r", timesteps: int = 128) -> None:
    from agents.cli import main

    assert main(["train", "--algo", "bppo", "--env", EASY, "--mode", "scratch", "--n-envs", "8",
                 "--hp", "n_steps=8", "--hp", "batch_size=32", "--timesteps", str(timesteps),
                 "--checkpoint-freq", "0", "--eval-freq", "0", "--no-final-eval", "--no-progress",
                 "--no-tensorboard", "--out", str(tmp_path), "--run-name", name, *extra]) == 0


# --- normalisers -------------------------------------------------------------------------------

def test_windowed_running_mean_forgets_geometrically():
    """With the count capped at W, a batch of B samples weighs B / (W + B): after a long run of
    zeros, k batches of ones leave the mean at 1 - (W / (W + B))^k (worked out by hand)."""
    from agents.training.batched_ppo import _RunningMeanStd

    W, B, k = 100, 10, 7
    rms = _RunningMeanStd((), window=W)
    for _ in range(50):
        rms.update(np.zeros(B))
    assert rms.count == W
    for _ in range(k):
        rms.update(np.ones(B))
    assert rms.mean == pytest.approx(1.0 - (W / (W + B)) ** k, abs=1e-12)
    # the variance: with q = W / (W + B) the update is var' = q var + (1 - q) q (1 - m)^2, which from
    # var ~ 0 after the zeros gives var_k = q^k (1 - q^k) = m_k (1 - m_k): a population that is
    # a share m_k of ones (the zeros' own variance, below 1e-5 after 50 batches, decays as q^k)
    m = rms.mean
    assert rms.var == pytest.approx(m * (1 - m), abs=1e-5)


def test_unwindowed_running_mean_never_forgets():
    """window=0 keeps every sample: 500 zeros then 70 ones give the plain mean 70 / 570."""
    from agents.training.batched_ppo import _RunningMeanStd

    rms = _RunningMeanStd((), window=0)
    for _ in range(50):
        rms.update(np.zeros(10))
    for _ in range(7):
        rms.update(np.ones(10))
    assert rms.mean == pytest.approx(70 / (570 + 1e-4), rel=1e-12)


def test_both_normalisers_forget_by_default_and_the_run_records_it(tmp_path):
    from agents.training.batched_ppo import BatchedPPO
    from agents.training.config import load_hyperparams

    assert BatchedPPO().obs_norm_window == BatchedPPO().reward_norm_window == 1_000_000
    hp = load_hyperparams("bppo", EASY, mode="scratch")
    assert hp["obs_norm_window"] == hp["reward_norm_window"] == 1_000_000
    _tiny_bppo(tmp_path, "--hp", "reward_norm_window=5000")
    run = tmp_path / "r"
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["training"]["obs_norm_window"] == 1_000_000 and cfg["training"]["reward_norm_window"] == 5000
    assert cfg["training"]["lr_schedule"] == "linear"
    stats = yaml.safe_load((run / "vecnormalize.json").read_text())
    assert stats["window"] == 1_000_000


# --- the evaluated policy is the trained one ---------------------------------------------------

OPTIONS = {"plain": [], "linear_skip": ["--hp", "policy_kwargs=dict(linear_skip=True)"],
           "recurrent": ["--hp", "policy_kwargs=dict(recurrent=True, gru_size=8)"],
           "privileged_critic": ["--hp", "policy_kwargs=dict(privileged_critic=True, linear_skip=True)"],
           "action_filter": ["--hp", "action_filter=0.5", "--hp", "policy_kwargs=dict(linear_skip=True)"],
           "squash": ["--hp", "policy_kwargs=dict(squash=True, linear_skip=True)"],
           "yaw_from": ["--hp", "yaw_from='PROPOSED_KF_DOB'", "--hp", "policy_kwargs=dict(linear_skip=True)"]}


@pytest.mark.parametrize("option", list(OPTIONS))
def test_predict_equals_the_training_time_actor(tmp_path, option):
    """For every policy option, a loaded agent's deterministic action is what the training loop
    computes on the same observations: features from a second builder run beside it,
    normalised, through the trunk (with its GRU state carried), the mean of ``heads`` (actor plus
    the linear skip term, which is made non-zero here) and the builder's action."""
    import gymnasium as gym
    import torch

    from agents.training.batched_obs import ObservationBuilder
    from agents.training.loading import load_agent

    _tiny_bppo(tmp_path, *OPTIONS[option])
    agent = load_agent(tmp_path / "r")
    net = agent.net
    if net.skip is not None:
        with torch.no_grad():  # make the skip term matter (it starts at zero)
            w = net.skip.weight
            w.copy_(torch.linspace(-0.5, 0.5, w.numel()).reshape(w.shape))
    ref = ObservationBuilder(agent.task_spec, **agent.builder_kwargs)  # the same features, built beside it
    env = gym.make_vec(EASY, num_envs=3, vectorization_mode="vector_entry_point")
    obs, _ = env.reset(seed=[11, 12, 13])
    start = np.ones(3, dtype=bool)
    h = net.initial_state(3)
    for _ in range(6):
        action, _ = agent.predict(obs, episode_start=start, deterministic=True)
        feats = agent.normalize(ref.observe(obs, start))
        with torch.no_grad():
            x, h = net.trunk(torch.as_tensor(feats, dtype=torch.float32), h, torch.as_tensor(start))
            mean, _ = net.heads(x, torch.zeros(3, net.priv) if net.priv else None)
            if net.skip is not None:
                assert np.abs(mean - net.actor(x)).max() > 1e-3  # the skip term is really part of the mean
        if net.squash:  # the env got tanh(a) in training
            mean = torch.tanh(mean)
        want = ref.act(mean.numpy().astype(np.float64))  # (act tells ref's observer the force: once per step)
        np.testing.assert_allclose(action, want, rtol=0, atol=1e-6)
        obs, *_ = env.step(action)
        start = np.zeros(3, dtype=bool)
    env.close()


# --- progress, seeds, logs ---------------------------------------------------------------------

def test_progress_lines_count_the_steps_collected():
    """A rollout of 16,384 steps in a 50,000-step budget prints one line with what was collected
    (32 %: rounded down, never overstated), not three lines that all say 16,384."""
    from agents.training.sb3 import _Progress

    out = io.StringIO()
    p = _Progress(50_000, 0, True, stream=out)
    for s in (16_384, 32_768, 49_152, 65_536):
        p.update(s)
    lines = out.getvalue().splitlines()
    assert lines == ["training: 32% (16,384/50,000 steps)", "training: 65% (32,768/50,000 steps)",
                     "training: 98% (49,152/50,000 steps)", "training: 100% (65,536/50,000 steps)"]


def test_bppo_budget_is_whole_rollouts_and_steps_done_matches(tmp_path):
    """130 steps with 8 envs x 8 steps per rollout: three rollouts (192 steps) are collected and
    recorded as both the budget and steps_done."""
    _tiny_bppo(tmp_path, timesteps=130)
    cfg = yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())
    assert cfg["steps_done"] == 192 == cfg["run"]["total_timesteps"]
    assert cfg["train_seconds"] > 0


def test_learning_curve_seeds_are_held_out_from_training_envs(tmp_path):
    from agents.training.config import ConfigError, TrainConfig
    from agents.training.runner import train

    default = TrainConfig(algo="bppo", env_id=EASY, mode="scratch")
    assert default.eval_seed >= 512 + default.seed  # the defaults are disjoint
    cfg = TrainConfig(algo="bppo", env_id=EASY, mode="scratch", n_envs=16, seed=0, eval_seed=10,
                      total_timesteps=128, out_dir=str(tmp_path), progress_bar=False)
    with pytest.raises(ConfigError, match=r"eval_seed.*10.*training env seeds 0-15") as e:
        train(cfg)
    assert e.value.field == "eval_seed" and not list(tmp_path.iterdir())


def test_episode_error_log_reads_the_env_metric():
    """The progress log's episode error is the env's own steady-state mean for episodes that
    ended (the key the vector env reports), never NaN when there is one."""
    from agents.training.batched_ppo import _episode_errors
    from auv_follow_env.metrics import METRIC_KEYS

    met = {k: np.array([0.25, 0.5]) for k in METRIC_KEYS}
    assert _episode_errors(met) == [0.25, 0.5]
    assert _episode_errors({}) == []


def test_episode_errors_are_logged_from_a_real_run(tmp_path):
    """Short episodes (2 s, steady state from 1 s) end during a tiny run: progress.csv's error column is finite."""
    _tiny_bppo(tmp_path, "--env-kwarg", "episode_s=2.0", "--env-kwarg", "steady_start_s=1.0",
               "--hp", "random_phase=False", timesteps=512)
    with open(tmp_path / "r" / "progress.csv") as f:
        vals = [float(r["ep_true_steady_mean_m"]) for r in csv.DictReader(f)]
    assert any(np.isfinite(v) and v > 0 for v in vals)


def test_train_command_defaults_to_the_batched_trainer():
    from agents.cli import build_parser

    assert build_parser().parse_args(["train"]).algo == "bppo"


# --- smoothness options ------------------------------------------------------------------------

def test_action_filter_is_a_first_order_low_pass_the_policy_observes():
    """alpha = 0.25 and a constant action 1 from an episode's start: the action used is
    u_k = 1 - 0.75^(k+1) and the observation carries u_{k-1} (0 at the start); a new episode
    starts from 0 again (worked out by hand)."""
    import gymnasium as gym

    from agents.training.batched_obs import ObservationBuilder

    env = gym.make(EASY)
    spec = env.unwrapped.task_spec
    raw, _ = env.reset(seed=1)
    env.close()
    b = ObservationBuilder(spec, observation="raw", action_filter=0.25)
    plain = ObservationBuilder(spec, observation="raw")
    assert b.dim == plain.dim + 3 and b.config["action_filter"] == 0.25 and "action_filter" not in plain.config
    raw2 = np.repeat(raw[None, :], 2, axis=0)
    start = np.array([True, True])
    for k in range(4):
        o = b.observe(raw2, start)
        np.testing.assert_allclose(o[:, -3:], 1 - 0.75 ** k, rtol=0, atol=1e-7)
        u = b.act(np.ones((2, 3)))
        np.testing.assert_allclose(u, 1 - 0.75 ** (k + 1), rtol=0, atol=1e-12)
        start = np.array([False, False])
    o = b.observe(raw2, np.array([True, False]))  # env 0 starts a new episode
    np.testing.assert_allclose(o[0, -3:], 0.0)
    np.testing.assert_allclose(o[1, -3:], 1 - 0.75 ** 4, atol=1e-7)


@pytest.mark.parametrize("value", [0, -0.1, 1.5, float("nan"), True, "x"])
def test_action_filter_refuses_values_outside_its_range(value):
    import gymnasium as gym

    from agents.training.batched_obs import ObservationBuilder

    env = gym.make(EASY)
    spec = env.unwrapped.task_spec
    env.close()
    with pytest.raises(ValueError, match=r"action_filter=.* must be a number in \(0, 1\]"):
        ObservationBuilder(spec, action_filter=value)


def test_smoothness_options_train_record_and_load(tmp_path):
    """Both options are bppo hyperparameters: recorded under training:, the filter also in the
    observation settings, and the loaded agent acts through the same filter."""
    from agents.training.loading import load_agent

    _tiny_bppo(tmp_path, "--hp", "action_rate_coef=0.1", "--hp", "action_filter=0.5")
    run = tmp_path / "r"
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["training"]["action_rate_coef"] == 0.1 and cfg["training"]["action_filter"] == 0.5
    assert cfg["observation"]["action_filter"] == 0.5
    with open(run / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert all(float(r["dF_u_mean_N"]) >= 0 for r in rows)
    agent = load_agent(run)
    assert agent.builder.action_filter == 0.5


def test_heading_term_is_zero_on_the_reference_heading_and_two_facing_away():
    """1 - cos(psi_ref - psi): 0 on the reference heading, 1 at 90 degrees, 2 facing the opposite
    way (by hand); no info, no term."""
    from agents.training.batched_ppo import _heading_penalty

    ref = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, 0.3], [0.0, 0.0, 0.3]])
    pose = np.array([[5.0, 1.0, 0.3], [5.0, 1.0, 0.3 + np.pi / 2], [5.0, 1.0, 0.3 - np.pi]])
    np.testing.assert_allclose(_heading_penalty({"true_reference": ref, "follower_pose": pose}, 3), [0, 1, 2],
                               atol=1e-12)
    np.testing.assert_array_equal(_heading_penalty({}, 2), [0.0, 0.0])


# --- speed without changing the maths ------------------------------------------------------------

def test_tanh_layers_equal_torch_tanh_and_its_derivative():
    """The actor's and critic's tanh (numpy's SIMD tanh) against the definition: values within a few
    float32 ulps of torch.tanh, and the gradient of sum(w * tanh(x)) is w (1 - tanh(x)^2), checked
    in float64 against math.tanh on a grid that covers saturation."""
    import math

    import torch

    from agents.training.batched_ppo import _numpy_tanh_module

    layer = _numpy_tanh_module()()
    x = torch.linspace(-20.0, 20.0, 4001, dtype=torch.float32).reshape(1, -1).repeat(3, 1)
    x.requires_grad_(True)
    y = layer(x)
    ref = torch.tensor([math.tanh(v) for v in x[0].tolist()], dtype=torch.float64)
    assert float((y[0].detach().double() - ref).abs().max()) <= 4 * 2.0 ** -24
    w = torch.randn(3, 4001, generator=torch.Generator().manual_seed(1))
    (w * y).sum().backward()
    expect = w.double() * (1.0 - ref ** 2)
    assert torch.allclose(x.grad.double(), expect, rtol=0.0, atol=1e-6)
    with torch.no_grad():  # the rollout's path (no autograd) gives the same values
        assert torch.equal(layer(x.detach()), y.detach())


def test_trainer_optimizer_follows_adams_rule_by_hand():
    """The trainer's optimizer (torch's fused Adam) against Adam's rule written out in float64
    (Kingma and Ba, with SB3's eps 1e-5) over five steps of given gradients: the same parameters
    within float32 rounding (a rule with eps 1e-8 would differ by up to lr)."""
    import torch

    from agents.training.batched_ppo import _adam, _build_net, _policy_kwargs

    net = _build_net(6, _policy_kwargs(None))
    opt = _adam(net, 3e-4)
    assert opt.defaults["fused"] is True
    params = list(net.parameters())
    p = [x.detach().double().numpy().copy() for x in params]
    m = [np.zeros_like(x) for x in p]
    v = [np.zeros_like(x) for x in p]
    rng = np.random.default_rng(7)
    b1, b2, lr, eps = 0.9, 0.999, 3e-4, 1e-5
    for k in range(1, 6):
        # gradients from 1e-6 to 1: eps matters for the small ones
        grads = [(rng.standard_normal(x.shape) * 10.0 ** rng.uniform(-6, 0, x.shape)).astype(np.float32)
                 for x in p]
        for x, g in zip(params, grads, strict=True):
            x.grad = torch.from_numpy(g.copy())
        opt.step()
        for i, g in enumerate(grads):
            m[i] = b1 * m[i] + (1 - b1) * g
            v[i] = b2 * v[i] + (1 - b2) * g.astype(np.float64) ** 2
            p[i] = p[i] - lr * (m[i] / (1 - b1 ** k)) / (np.sqrt(v[i] / (1 - b2 ** k)) + eps)
    for x, want in zip(params, p, strict=True):
        np.testing.assert_allclose(x.detach().double().numpy(), want, rtol=1e-5, atol=1e-7)


def test_run_records_where_its_wall_clock_went(tmp_path):
    """result.phase_seconds splits the training loop: every part >= 0 (other within timer noise)
    and the parts add up to the loop's wall clock; a residual's base controller is timed apart."""
    _tiny_bppo(tmp_path, "--mode", "residual", "--controller", "PROPOSED_KF_DOB", timesteps=256)
    cfg = yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())
    ph = cfg["result"]["phase_seconds"]
    assert set(ph) == {"physics", "filter_observer", "base_controller", "policy_forward", "update", "other"}
    assert all(ph[k] > 0 for k in ("physics", "filter_observer", "base_controller", "policy_forward", "update"))
    assert ph["other"] > -0.01
    assert abs(sum(ph.values()) - cfg["result"]["wall_clock_s"]) < 0.02
    assert cfg["threads"]["torch"] == 2



def test_bounds_loss_pulls_a_saturated_mean_back_inside_the_action_box():
    """A mean beyond the env's box [-1, 1] is clipped by the env, so PPO's own gradient cannot move
    it; with bounds_loss_coef the loss gains c * sum relu(|mu| - 1)^2: with zero advantages and
    returns equal to the values (no other gradient) updates bring a yaw mean of 1.5 back to 1
    and leave a mean inside the box alone."""
    import torch

    from agents.training.batched_ppo import BatchedPPO, _build_net, _policy_kwargs, _update

    torch.manual_seed(0)
    net = _build_net(6, _policy_kwargs({}))
    with torch.no_grad():
        net.actor[-1].weight.zero_()
        net.actor[-1].bias.copy_(torch.tensor([0.5, 0.0, 1.5]))
        for p in net.critic.parameters():
            p.zero_()
    opt = torch.optim.Adam(net.parameters(), lr=0.05)
    T, N = 4, 16
    obs = torch.randn(T, N, 6).numpy()
    act = np.zeros((T, N, 3), dtype=np.float32)
    with torch.no_grad():
        mean = net.mean(torch.from_numpy(obs))
        std = torch.exp(net.log_std)
        logp = (-0.5 * ((torch.from_numpy(act) - mean) / std) ** 2 - torch.log(std)
                - 0.5 * np.log(2 * np.pi)).sum(-1).numpy()
    hp = {**BatchedPPO().__dict__, "batch_size": 64, "n_epochs": 1, "bounds_loss_coef": 1.0}
    zeros = np.zeros((T, N), dtype=np.float32)
    for _ in range(60):
        _update(net, opt, hp, obs, None, np.zeros((T, N), bool), act, logp, zeros, zeros, np.ones((T, N), bool),
                None, -5.0)
    with torch.no_grad():
        m = net.mean(torch.from_numpy(obs)).numpy()
    assert np.all(np.abs(m[..., 2]) < 1.05)
    np.testing.assert_allclose(m[..., 0], 0.5, atol=0.05)


def test_squashed_policy_acts_with_tanh_of_its_mean_inside_the_box(tmp_path):
    """With policy_kwargs squash=True the env action is tanh of the Gaussian's draw: a loaded
    agent whose mean is (0.5, 0, 1.5) commands tanh(0.5) = 0.46212 and tanh(1.5) = 0.90515 (hand
    values), inside the box; a mean of 3 still moves the action (tanh 3 = 0.99505), where an
    unsquashed mean of 1.5 or 3 is clipped to the same 1."""
    import torch

    from agents.training.loading import load_agent

    _tiny_bppo(tmp_path, "--hp", "policy_kwargs=dict(squash=True)")
    agent = load_agent(tmp_path / "r")
    assert agent.net.squash
    obs = np.zeros((2, 20))
    for yaw, want in ((1.5, 0.90515), (3.0, 0.99505)):
        with torch.no_grad():
            agent.net.actor[-1].weight.zero_()
            agent.net.actor[-1].bias.copy_(torch.tensor([0.5, 0.0, yaw]))
        agent.reset()
        a, _ = agent.predict(obs, deterministic=True)
        np.testing.assert_allclose(a[:, 0], 0.46212, atol=1e-5)
        np.testing.assert_allclose(a[:, 2], want, atol=1e-5)


def test_yaw_rate_term_is_the_squared_yaw_rate_of_the_observation():
    """yaw_rate_coef's penalty reads the follower's yaw rate from the raw observation (field r):
    a spin at 5 rad/s costs 25 c per step, a straight course nothing; recorded in config.yaml."""
    from agents.training.batched_ppo import _yaw_rate_penalty
    from auv_follow_env.layout import OBS_DIM_V1, OBS_INDEX

    raw = np.zeros((3, OBS_DIM_V1))
    raw[:, OBS_INDEX["r"]] = [5.0, -0.2, 0.0]
    raw[:, OBS_INDEX["u"]] = 1.0  # other fields do not count
    np.testing.assert_allclose(_yaw_rate_penalty(raw), [25.0, 0.04, 0.0])


def test_yaw_rate_option_trains_and_is_recorded(tmp_path):
    _tiny_bppo(tmp_path, "--hp", "yaw_rate_coef=0.05")
    cfg = yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())
    assert cfg["training"]["yaw_rate_coef"] == 0.05


def test_yaw_from_a_classical_law_replaces_only_the_yaw_moment():
    """yaw_from: the env gets the agent's surge and sway and the classical law's yaw moment (the
    action that law alone would command on the same observations), its observer is told the
    force applied; the option is recorded in the builder's config and refused with a residual."""
    import gymnasium as gym

    from agents.training.batched_obs import ObservationBuilder
    from controllers import make_controller

    env = gym.make_vec(EASY, num_envs=4, vectorization_mode="vector_entry_point")
    spec = env.unwrapped.task_spec
    b = ObservationBuilder(spec, observation="estimator", yaw_from="PROPOSED_KF_DOB")
    law = make_controller("PROPOSED_KF_DOB", spec)
    assert b.config["yaw_from"] == "PROPOSED_KF_DOB"
    assert "yaw_from" not in ObservationBuilder(spec, observation="estimator").config
    obs, _ = env.reset(seed=[21, 22, 23, 24])
    start = np.ones(4, dtype=bool)
    rng = np.random.default_rng(3)
    for _ in range(30):
        b.observe(obs, start)
        want, _ = law.predict(np.asarray(obs, dtype=np.float64), episode_start=start)
        agent = rng.uniform(-1.0, 1.0, (4, 3))
        a = b.act(agent)
        np.testing.assert_array_equal(a[:, :2], agent[:, :2])
        np.testing.assert_array_equal(a[:, 2], want[:, 2].astype(np.float64))
        np.testing.assert_array_equal(b.yaw_base.disturbance_observer._f, np.clip(a * b.limits, -b.limits, b.limits))
        law.disturbance_observer.applied(a * b.limits)  # the law beside it is told the same force
        obs, *_ = env.step(a)
        start = np.zeros(4, dtype=bool)
    env.close()
    with pytest.raises(ValueError, match=r"yaw_from='PROPOSED_KF_DOB' is invalid with mode='residual'"):
        ObservationBuilder(spec, mode="residual", controller="PROPOSED_KF_DOB", yaw_from="PROPOSED_KF_DOB")
    with pytest.raises(ValueError, match=r"yaw_from='LQR' is invalid"):
        ObservationBuilder(spec, yaw_from="LQR")


def test_training_log_error_mean_skips_episodes_without_a_steady_state():
    """progress.csv's ep_true_steady_mean_m: episodes that ended before t = 10 s have no steady
    error (NaN); the mean is over the others, and a batch with none is NaN without a numpy warning."""
    import warnings

    from agents.training.batched_ppo import _finite_mean

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _finite_mean([0.02, float("nan"), 0.04]) == pytest.approx(0.03)
        assert math.isnan(_finite_mean([float("nan"), float("nan")]))
        assert math.isnan(_finite_mean([]))
