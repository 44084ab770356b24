"""The envs with the tools users bring: Gymnasium's vector API (autoreset modes), TorchRL, skrl,
rl-zoo3 with the shipped hyperparameter files and a CleanRL-style loop with the usual wrappers.

Each run is a few hundred steps. The expectations come from the single env run by hand with
the same seeds and actions (its episodes are the reference), not from the tool under test. A
tool that is not installed is skipped with the reason; the dev extra installs all of them.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import auv_follow_env  # noqa: F401
from auv_follow_env.params import UnknownKeywordError
from auv_follow_env.vector_env import AUVFollowVectorEnv

ROOT = Path(__file__).resolve().parent.parent
S4 = "AUVFollow-S4-v0"
SHORT = {"episode_s": 2.0, "steady_start_s": 1.0}  # 40 steps of 0.05 s
SHORT_VEC = {**SHORT, "max_episode_steps": 40}


def _action(i: int, j: int, t: int) -> np.ndarray:
    """A fixed action for env i, episode j, step t of the episode (the same in every mode)."""
    return np.array([np.sin(0.3 * t + i + 2 * j), np.cos(0.2 * t - i), np.sin(0.1 * t * j + 1.0)], dtype=np.float32)


def _single_episodes(env_id: str, seed: int, n_episodes: int, i: int, kw: dict, first_episode: int = 0):
    """The reference: a single env reset with ``seed`` once and then without a seed, stepped
    with :func:`_action`; episodes ``first_episode`` .. as (observations, rewards, ends)."""
    env = gym.make(env_id, **kw)
    out = []
    for j in range(first_episode + n_episodes):
        obs, _ = env.reset(seed=seed) if j == 0 else env.reset()
        o, r, ends = [obs], [], []
        t = 0
        while True:
            obs, rew, term, trunc, _ = env.step(_action(i, j - first_episode, t))
            t += 1
            o.append(obs)
            r.append(rew)
            ends.append((term, trunc))
            if term or trunc:
                break
        if j >= first_episode:
            out.append((np.array(o), np.array(r), ends))
    env.close()
    return out


def _vector_episodes(env_id: str, mode: AutoresetMode, n: int, steps: int, seed: int, kw: dict):
    """Run the native vector env in ``mode`` with :func:`_action` on each episode's own steps;
    returns, per env, its completed episodes as (observations, rewards, ends)."""
    venv = gym.make_vec(env_id, num_envs=n, autoreset_mode=mode, **kw)
    assert venv.autoreset_mode is mode and venv.metadata["autoreset_mode"] is mode
    obs, _ = venv.reset(seed=seed)
    cur = [([obs[i].copy()], [], []) for i in range(n)]
    done_eps: list[list] = [[] for _ in range(n)]
    episode = [0] * n
    t = [0] * n
    waiting = np.zeros(n, dtype=bool)  # NEXT_STEP: the next step is the reset
    for _ in range(steps):
        a = np.stack([_action(i, episode[i], t[i]) for i in range(n)])
        obs, rew, term, trunc, info = venv.step(a)
        for i in range(n):
            if waiting[i]:
                assert rew[i] == 0.0 and not term[i] and not trunc[i]
                cur[i] = ([obs[i].copy()], [], [])
                waiting[i] = False
                continue
            ended = term[i] or trunc[i]
            last = obs[i]
            if mode is AutoresetMode.SAME_STEP:
                # (as SyncVectorEnv's, the keys exist on the steps where some episode ended)
                none = np.zeros(n, dtype=bool)
                assert info.get("_final_obs", none)[i] == ended and info.get("_final_info", none)[i] == ended
                if ended:
                    last = info["final_obs"][i]
                    assert info["final_info"]["_episode_metrics"][i]
            cur[i][0].append(last.copy())
            cur[i][1].append(rew[i])
            cur[i][2].append((bool(term[i]), bool(trunc[i])))
            t[i] += 1
            if ended:
                done_eps[i].append((np.array(cur[i][0]), np.array(cur[i][1]), cur[i][2]))
                episode[i] += 1
                t[i] = 0
                if mode is AutoresetMode.NEXT_STEP:
                    waiting[i] = True
                elif mode is AutoresetMode.SAME_STEP:
                    cur[i] = ([obs[i].copy()], [], [])  # the new episode's first observation
        if mode is AutoresetMode.DISABLED and (term | trunc).any():
            obs, _ = venv.reset(options={"reset_mask": term | trunc})
            for i in np.flatnonzero(term | trunc):
                cur[i] = ([obs[i].copy()], [], [])
    venv.close()
    return done_eps


# --- unknown keywords ------------------------------------------------------------------


def test_unknown_keywords_are_type_errors_naming_them_and_the_valid_ones():
    """``gym.make(id, frameskip=...)``: a TypeError in Python's words (what TorchRL looks for to
    drop the keyword), naming every unknown keyword and listing the valid overrides; a bad
    value of a known keyword stays a ValueError."""
    for make in (lambda **kw: gym.make(S4, **kw), lambda **kw: gym.make("AUVFollow-Hard-v1", **kw),
                 lambda **kw: gym.make_vec(S4, num_envs=2, **kw),
                 lambda **kw: auv_follow_env.make_task_spec("S4", **kw)):
        with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'") as exc:
            make(frameskip=4)
        assert isinstance(exc.value, UnknownKeywordError) and "delay_s" in str(exc.value)
        with pytest.raises(TypeError) as exc:
            make(frameskip=None, foo=1)  # (None too: an unknown keyword is never "no override")
        assert "unexpected keyword argument 'foo'" in str(exc.value)
        assert "unexpected keyword argument 'frameskip'" in str(exc.value)
        with pytest.raises(ValueError, match="delay_s") as exc:
            make(delay_s="two")
        assert not isinstance(exc.value, TypeError)
    with pytest.raises(TypeError, match="loss_prob.*exist only on the v1 ids"):
        gym.make(S4, loss_prob=0.1)


# --- vector env: autoreset modes --------------------------------------------------------


@pytest.mark.parametrize("env_id,kw", [(S4, {**SHORT_VEC, "max_distance_m": 2.2}),
                                       ("AUVFollow-Hard-v1", SHORT_VEC)])
def test_episodes_are_the_same_in_every_autoreset_mode(env_id, kw):
    """Same seeds, same actions on each episode's steps: NEXT_STEP, SAME_STEP and DISABLED give
    the single env's episodes, one by one, bit for bit (truncations at 40 steps and, with
    max_distance_m=2.2 m on S4, terminations at other lengths)."""
    n, seed = 3, 7
    runs = {mode: _vector_episodes(env_id, mode, n, 130, seed, kw) for mode in AutoresetMode}
    single_kw = {k: v for k, v in kw.items() if k != "max_episode_steps"}
    lengths: set[int] = set()
    for i in range(n):
        counts = {mode: len(runs[mode][i]) for mode in AutoresetMode}
        # NEXT_STEP spends one step per autoreset, so it completes fewer episodes in 130 steps
        assert counts[AutoresetMode.SAME_STEP] == counts[AutoresetMode.DISABLED] >= counts[AutoresetMode.NEXT_STEP] >= 3
        ref = _single_episodes(env_id, seed + i, counts[AutoresetMode.SAME_STEP], i, single_kw)
        lengths |= {len(r) for _, r, _ in ref}
        for mode in AutoresetMode:
            for j, (obs, rew, ends) in enumerate(runs[mode][i]):
                np.testing.assert_array_equal(obs, ref[j][0], err_msg=f"{mode} env {i} episode {j}")
                np.testing.assert_array_equal(rew, ref[j][1], err_msg=f"{mode} env {i} episode {j}")
                assert ends == ref[j][2]
    if env_id == S4:
        assert 40 in lengths and len(lengths) > 1  # truncations and terminations both occur


def test_same_step_info_matches_sync_vector_env():
    """SAME_STEP's info has SyncVectorEnv's layout: final_obs (an object array, None where no
    episode ended), final_info (the ended envs' step info, episode_metrics in it), the masks
    _final_obs / _final_info; values equal to gymnasium's SyncVectorEnv over single envs."""
    n = 3
    mode = AutoresetMode.SAME_STEP
    native = gym.make_vec(S4, num_envs=n, autoreset_mode=mode, **SHORT_VEC)
    sync = gym.make_vec(S4, num_envs=n, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode}, **SHORT)
    assert isinstance(native, AUVFollowVectorEnv) and isinstance(sync, gym.vector.SyncVectorEnv)
    o1, _ = native.reset(seed=3)
    o2, _ = sync.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    ends = 0
    for t in range(90):
        a = np.stack([_action(i, 0, t) for i in range(n)])
        r1, r2 = native.step(a), sync.step(a)
        for x, y in zip(r1[:4], r2[:4], strict=True):
            np.testing.assert_array_equal(x, y)
        i1, i2 = r1[4], r2[4]
        assert ("final_obs" in i1) == ("final_obs" in i2)
        if "final_obs" in i2:
            ends += 1
            np.testing.assert_array_equal(i1["_final_obs"], i2["_final_obs"])
            np.testing.assert_array_equal(i1["_final_info"], i2["_final_info"])
            for k in range(n):
                if i2["_final_obs"][k]:
                    np.testing.assert_array_equal(i1["final_obs"][k], i2["final_obs"][k])
                else:
                    assert i1["final_obs"][k] is None
            f1, f2 = i1["final_info"], i2["final_info"]
            m = i2["_final_info"]
            for key in ("tracking_error", "time", "follower_pose"):
                np.testing.assert_array_equal(f1[key][m], f2[key][m])
            for key in ("rmse", "max", "mean"):
                got = [key_ for key_ in f1["episode_metrics"] if key_.endswith(key) and not key_.startswith("_")]
                for name in got:
                    np.testing.assert_array_equal(f1["episode_metrics"][name][m], f2["episode_metrics"][name][m])
            np.testing.assert_array_equal(i1["time"], i2["time"])  # the new episodes' time, 0
    assert ends == 2  # at steps 40 and 80


def test_autoreset_mode_is_checked_and_disabled_needs_the_caller_to_reset():
    for bad in ("same", 1, True, object()):
        with pytest.raises(ValueError, match="autoreset_mode=.*SAME_STEP"):
            AUVFollowVectorEnv(num_envs=2, autoreset_mode=bad)
    for given, want in (("SameStep", AutoresetMode.SAME_STEP), ("DISABLED", AutoresetMode.DISABLED),
                        (None, AutoresetMode.NEXT_STEP)):
        assert AUVFollowVectorEnv(num_envs=2, autoreset_mode=given).autoreset_mode is want
    assert AUVFollowVectorEnv(num_envs=2).metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
    venv = gym.make_vec(S4, num_envs=2, autoreset_mode=AutoresetMode.DISABLED, **SHORT_VEC)
    venv.reset(seed=0)
    a = np.zeros((2, 3))
    for _ in range(40):
        obs, _, _, trunc, info = venv.step(a)
    assert trunc.all() and "_episode_metrics" in info
    k = venv.unwrapped._sim.k.copy()
    with pytest.raises(RuntimeError, match=r"envs \[0, 1\].*reset_mask"):
        venv.step(a)
    np.testing.assert_array_equal(venv.unwrapped._sim.k, k)  # nothing was stepped
    obs2, _ = venv.reset(options={"reset_mask": np.array([True, False])})
    np.testing.assert_array_equal(obs2[1], obs[1])
    with pytest.raises(RuntimeError, match=r"envs \[1\]"):
        venv.step(a)


# --- TorchRL -----------------------------------------------------------------------------


def _zero_policy(td):
    import torch

    return td.set("action", torch.zeros(td.batch_size + (3,)))


def test_torchrl_gym_env_and_wrapper_single():
    """``GymEnv(id)`` (TorchRL passes frameskip and drops it on our TypeError) and
    ``GymWrapper(gym.make(id))``: specs check, 300 steps; TorchRL resets after set_seed, so the
    rollout is the single env's second episode from that seed."""
    pytest.importorskip("torchrl", reason="TorchRL is not installed (pip install -e '.[dev]')")
    from torchrl.envs import GymEnv, GymWrapper
    from torchrl.envs.utils import check_env_specs

    env = GymEnv(S4, **SHORT)
    check_env_specs(env)
    env.set_seed(5)
    td = env.rollout(300, policy=_zero_policy, break_when_any_done=False)
    assert td.batch_size == (300,) and td["next", "observation"].shape == (300, 16)
    assert int(td["next", "truncated"].sum()) == 7  # 300 steps of 40-step episodes
    ref = gym.make(S4, **SHORT)
    ref.reset(seed=5)
    obs, _ = ref.reset()
    np.testing.assert_array_equal(td["observation"][0].numpy(), obs)
    rewards = [ref.step(np.zeros(3, np.float32))[1] for _ in range(40)]
    np.testing.assert_array_equal(td["next", "reward"][:40, 0].numpy(), np.float32(rewards))

    w = GymWrapper(gym.make("AUVFollow-Hard-v1", **SHORT))
    check_env_specs(w)
    td = w.rollout(300, break_when_any_done=False)
    assert td["next", "observation"].shape == (300, 20) and int(td["next", "done"].sum()) == 7


def test_torchrl_gym_wrapper_on_the_vector_env():
    """``GymWrapper(gym.make_vec(id, num_envs=4, autoreset_mode=...))``: TorchRL refuses NEXT_STEP
    and runs SAME_STEP and DISABLED. DISABLED's rollout is each env's single-env episodes; under
    SAME_STEP the step that ends an episode carries its last observation (from final_obs)."""
    pytest.importorskip("torchrl", reason="TorchRL is not installed (pip install -e '.[dev]')")
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    with pytest.raises(RuntimeError, match="SAME_STEP or DISABLED"):
        GymWrapper(gym.make_vec(S4, num_envs=4, **SHORT_VEC))
    n = 4
    refs = [[np.array(o) for o in _zero_episodes(i)] for i in range(n)]
    for mode in (AutoresetMode.SAME_STEP, AutoresetMode.DISABLED):
        w = GymWrapper(gym.make_vec(S4, num_envs=n, autoreset_mode=mode, **SHORT_VEC))
        assert w.batch_size == (n,)
        check_env_specs(w)
        w.set_seed(11)
        td = w.rollout(300, policy=_zero_policy, break_when_any_done=False)
        assert td.batch_size == (n, 300)
        assert int(td["next", "done"].sum()) == n * 7
        for i in range(n):
            # the first episode of the rollout is the second after the seeded reset (as single)
            np.testing.assert_array_equal(td["observation"][i, :40].numpy(), refs[i][1][:40])
            np.testing.assert_array_equal(td["next", "observation"][i, :40].numpy(), refs[i][1][1:])
            if mode is AutoresetMode.DISABLED:
                np.testing.assert_array_equal(td["observation"][i, 40:80].numpy(), refs[i][2][:40])


@pytest.mark.parametrize("env_id", ["AUVFollow-Hard-v1", "AUVFollow-Leader-Hard-v1"])
def test_torchrl_gym_wrapper_on_the_v1_vector_env(env_id):
    """``GymWrapper(gym.make_vec("AUVFollow-Hard-v1", num_envs=4, autoreset_mode=SAME_STEP))`` failed:
    the fixed current ranges were one tuple object per env, which TorchRL stacked as (2, 4). Now every
    info array leads with the env axis: a range is a float (N, 2) array, NaN for envs not reset."""
    pytest.importorskip("torchrl", reason="TorchRL is not installed (pip install -e '.[dev]')")
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    n = 4
    vec = gym.make_vec(env_id, num_envs=n, autoreset_mode=AutoresetMode.SAME_STEP)
    _, info = vec.reset(seed=3)
    single = gym.make(env_id).reset(seed=3)[1]["condition"]["current_x"]  # the single env's: a (lo, hi) tuple
    cx = info["condition"]["current_x"]
    assert cx.shape == (n, 2) and cx.dtype == np.float64
    np.testing.assert_array_equal(cx, np.tile(np.asarray(single, dtype=float), (n, 1)))
    _, info = vec.reset(seed=3, options={"reset_mask": np.array([True, False, True, False])})
    cx = info["condition"]["current_x"]
    assert np.isnan(cx[[1, 3]]).all() and np.isfinite(cx[[0, 2]]).all()
    w = GymWrapper(vec)
    assert w.batch_size == (n,)
    check_env_specs(w)
    td = w.rollout(50, policy=_zero_policy, break_when_any_done=False)
    assert td.batch_size == (n, 50) and td["next", "observation"].shape == (n, 50, 20)
    assert bool(td["next", "observation"].isfinite().all())


def _zero_episodes(i: int, seed: int = 11) -> list[list[np.ndarray]]:
    """Env i of a vector env seeded ``seed``: its first three episodes' observations under
    zero actions, from the single env."""
    env = gym.make(S4, **SHORT)
    out = []
    for j in range(3):
        obs, _ = env.reset(seed=seed + i) if j == 0 else env.reset()
        o = [obs]
        for _ in range(40):
            o.append(env.step(np.zeros(3, np.float32))[0])
        out.append(o)
    return out


# --- skrl --------------------------------------------------------------------------------


@pytest.mark.parametrize("vector", [False, True])
def test_skrl_gymnasium_wrapper(vector):
    pytest.importorskip("skrl", reason="skrl is not installed (pip install -e '.[dev]')")
    import torch
    from skrl.envs.wrappers.torch import wrap_env

    env = gym.make_vec(S4, num_envs=4, **SHORT_VEC) if vector else gym.make(S4, **SHORT)
    w = wrap_env(env, wrapper="gymnasium")
    n = 4 if vector else 1
    assert w.num_envs == n and w.observation_space.shape == (16,) and w.action_space.shape == (3,)
    obs, _ = w.reset()
    assert obs.shape == (n, 16)
    ends = 0
    for _ in range(300):
        obs, rew, term, trunc, _ = w.step(torch.zeros(n, 3))
        assert obs.shape == (n, 16) and rew.shape == (n, 1) and torch.isfinite(rew).all()
        ends += int((term | trunc).sum())
        if not vector and (term | trunc).any():
            obs, _ = w.reset()
    # 300 steps of 40-step episodes: 7 ends per env (the vector env's autoreset steps in between
    # end the last one at step 286)
    assert ends == n * 7
    w.close()


# --- rl-zoo3 -----------------------------------------------------------------------------


@pytest.mark.parametrize("algo", ["ppo", "sac", "td3", "recurrentppo", "bppo"])
def test_rl_zoo_reads_the_shipped_files_as_load_hyperparams_does(algo, tmp_path, capsys):
    """rl-zoo3's own reader (ExperimentManager.read_hyperparameters, with -conf) and
    agents.train.load_hyperparams give the same hyperparameters for every section of every
    shipped file and for an env id without a section (the default); numbers are numbers."""
    pytest.importorskip("rl_zoo3", reason="rl-zoo3 is not installed (pip install -e '.[dev]')")
    import yaml
    from rl_zoo3.exp_manager import ExperimentManager

    from agents.training.config import _eval_zoo, load_hyperparams

    path = ROOT / "agents" / "training" / "hyperparams" / f"{algo}.yml"
    sections = [k for k in yaml.safe_load(path.read_text()) if k not in ("default", "residual")]
    for env_id in sections + ["AUVFollow-Hard-v1"]:
        zoo = ExperimentManager(argparse.Namespace(), "ppo", env_id, str(tmp_path), config=str(path))
        hp, _ = zoo.read_hyperparameters()
        ours = load_hyperparams(algo, env_id, path, mode="scratch")
        assert {k: _eval_zoo(v, k) for k, v in hp.items()} == ours, env_id
        assert isinstance(hp["n_timesteps"], int) and hp["n_timesteps"] > 0
        for key in ("learning_rate", "gamma", "batch_size", "n_steps"):
            if key in hp:
                assert isinstance(hp[key], (int, float)) and not isinstance(hp[key], bool), (env_id, key)
    capsys.readouterr()


def test_rl_zoo_trains_with_the_shipped_ppo_file(tmp_path):
    """``python -m rl_zoo3.train --algo ppo --env AUVFollow-S4-v0 --gym-packages auv_follow_env
    -conf agents/training/hyperparams/ppo.yml`` with the zoo's ``-n`` cut to 64 steps (PPO still collects
    one rollout of n_steps x n_envs = 4096 steps): it trains and saves, with the file's settings."""
    pytest.importorskip("rl_zoo3", reason="rl-zoo3 is not installed (pip install -e '.[dev]')")
    cmd = [sys.executable, "-m", "rl_zoo3.train", "--algo", "ppo", "--env", S4, "--gym-packages", "auv_follow_env",
           "-conf", str(ROOT / "agents" / "training" / "hyperparams" / "ppo.yml"), "-n", "64", "-f", str(tmp_path),
           "--eval-freq", "-1", "--save-freq", "-1", "--seed", "0", "--num-threads", "1", "--verbose", "0"]
    res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    run = tmp_path / "ppo" / f"{S4}_1"
    assert (run / f"{S4}.zip").is_file() and (run / S4 / "vecnormalize.pkl").is_file()
    import yaml

    saved = dict(yaml.unsafe_load((run / S4 / "config.yml").read_text()))  # (the zoo writes an OrderedDict)
    assert saved["policy"] == "MlpPolicy" and saved["n_steps"] == 512 and saved["n_envs"] == 8
    assert saved["n_timesteps"] == 3_000_000  # the env's own section, read as a number


# --- CleanRL-style loop -------------------------------------------------------------------


def test_cleanrl_style_loop_with_the_standard_wrappers():
    """CleanRL's continuous-action env stack on gym.vector.SyncVectorEnv, 300 steps: episode
    statistics before normalisation (length 40, return = the raw rewards' sum, checked against
    a bare env with the same seed and actions), clipped observations and rewards."""
    gamma = 0.99

    def make(i: int):
        def thunk():
            env = gym.make(S4, **SHORT)
            env = gym.wrappers.RecordEpisodeStatistics(env)
            env = gym.wrappers.ClipAction(env)
            env = gym.wrappers.NormalizeObservation(env)
            env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10), env.observation_space)
            env = gym.wrappers.NormalizeReward(env, gamma=gamma)
            env = gym.wrappers.TransformReward(env, lambda r: np.clip(r, -10, 10))
            return env
        return thunk

    envs = gym.vector.SyncVectorEnv([make(i) for i in range(2)])
    bare = gym.make(S4, **SHORT)
    obs, _ = envs.reset(seed=1)
    bare.reset(seed=1)
    rng = np.random.default_rng(0)
    raw_return, episodes = 0.0, []
    reset_next = False
    for _ in range(300):
        a = rng.uniform(-1.5, 1.5, (2, 3)).astype(np.float32)  # (ClipAction clips to [-1, 1])
        obs, rew, term, trunc, info = envs.step(a)
        assert np.all(np.abs(obs) <= 10) and np.all(np.abs(rew) <= 10)
        if reset_next:  # NEXT_STEP: this step reset the envs
            bare.reset()
            reset_next = False
        else:
            raw_return += bare.step(np.clip(a[0], -1, 1))[1]
        if "episode" in info and info["_episode"][0]:
            episodes.append((float(info["episode"]["r"][0]), int(info["episode"]["l"][0]), raw_return))
            raw_return = 0.0
            reset_next = True
    assert len(episodes) == 7
    for r, length, expected in episodes:
        assert length == 40
        assert r == pytest.approx(expected, rel=1e-6)  # (RecordEpisodeStatistics keeps float32-rounded times)
    envs.close()
