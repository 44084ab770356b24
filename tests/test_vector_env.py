"""AUVFollowVectorEnv: batch-vs-single equivalence across resets and autoresets, seeding,
action validation, the Gymnasium vector API (make_vec, info masks, wrappers)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers.vector import DictInfoToList, RecordEpisodeStatistics

import auv_follow_env
from auv_follow_env.metrics import METRIC_KEYS
from auv_follow_env.vector_env import AUVFollowVectorEnv

ID = "AUVFollow-S4-v0"
SHORT = {"episode_s": 2.0, "steady_start_s": 1.0, "max_episode_steps": 40}  # 40 steps: several autoresets per test
TERMINATING = {**SHORT, "max_distance_m": 2.5}  # random forces drift past 2.5 m at various steps
INFO_KEYS = ("tracking_error", "time", "true_target", "true_reference", "follower_pose")


def _actions(steps: int, n: int, seed: int = 1) -> np.ndarray:
    """Random actions, partly outside [-1, 1] so clipping is exercised."""
    return np.random.default_rng(seed).uniform(-1.2, 1.2, (steps, n, 3)).astype(np.float32)


def _vec(n: int, kwargs: dict, env_id: str = ID) -> gym.vector.VectorEnv:
    return gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kwargs)


def _single_rollout(env: gym.Env, seed: int, actions: np.ndarray) -> list[tuple]:
    """Env driven with next-step autoreset by hand: reset(seed) once, then reset() after each end."""
    obs, info = env.reset(seed=seed)
    out = [(obs, None, False, False, info)]
    done = False
    for a in actions:
        if done:
            obs, info = env.reset()
            out.append((obs, 0.0, False, False, info))
            done = False
        else:
            obs, rew, term, trunc, info = env.step(a)
            out.append((obs, rew, term, trunc, info))
            done = term or trunc
    return out


def _vec_rollout(venv: gym.vector.VectorEnv, seed, actions: np.ndarray) -> list[tuple]:
    obs, info = venv.reset(seed=seed)
    out = [(obs, None, None, None, info)]
    for a in actions:
        out.append(venv.step(a))
    return out


def _assert_env_matches(vec: list[tuple], single: list[tuple], i: int) -> int:
    """Env i of a vector rollout equals a single-env rollout, bit for bit; returns #episode ends."""
    ends = 0
    for t, ((vo, vr, vte, vtr, vinfo), (so, sr, ste, str_, sinfo)) in enumerate(zip(vec, single, strict=True)):
        where = f"env {i}, step {t}"
        np.testing.assert_array_equal(vo[i], so, err_msg=where)
        if t > 0:
            assert vr[i] == sr, where
            assert vte[i] == ste and vtr[i] == str_, where
        for key in INFO_KEYS:
            np.testing.assert_array_equal(vinfo[key][i], sinfo[key], err_msg=f"{where}, {key}")
            assert vinfo[f"_{key}"][i]
        ended = "episode_metrics" in sinfo
        assert bool(vinfo.get("_episode_metrics", np.zeros(len(vo), bool))[i]) == ended, where
        if ended:
            ends += 1
            for key in METRIC_KEYS:
                np.testing.assert_array_equal(vinfo["episode_metrics"][key][i], sinfo["episode_metrics"][key],
                                              err_msg=f"{where}, {key}")
        elif "episode_metrics" in vinfo:
            assert all(np.isnan(vinfo["episode_metrics"][key][i]) for key in METRIC_KEYS)
    return ends


@pytest.mark.parametrize("kwargs, steps", [(SHORT, 130), (TERMINATING, 130)], ids=["truncation", "termination"])
def test_every_env_reproduces_the_single_env_across_autoresets(kwargs, steps):
    n, seed = 5, 11
    actions = _actions(steps, n)
    vec = _vec_rollout(_vec(n, kwargs), seed, actions)
    terms = truncs = 0
    for i in range(n):
        single = _single_rollout(gym.make(ID, **kwargs), seed + i, actions[:, i])
        assert _assert_env_matches(vec, single, i) >= 2
        terms += sum(bool(s[2]) for s in single)
        truncs += sum(bool(s[3]) for s in single)
    assert truncs >= 2
    if kwargs is TERMINATING:
        assert terms >= 3  # terminations at different steps in different envs


def test_vector_entry_point_equals_sync_vector_env():
    n, seed, steps = 4, 3, 90
    actions = _actions(steps, n, seed=7)
    native = _vec_rollout(_vec(n, TERMINATING), seed, actions)
    sync = _vec_rollout(gym.make_vec(ID, num_envs=n, vectorization_mode="sync", **TERMINATING), seed, actions)
    ends = 0
    for t, (a, b) in enumerate(zip(native, sync, strict=True)):
        for x, y in zip(a[:4], b[:4], strict=True):
            if t > 0 or x is not None:
                assert data_equivalence(x, y, exact=True), f"step {t}"
        ia, ib = a[4], b[4]
        assert set(ia) == set(ib), f"step {t}"
        for key in INFO_KEYS:
            assert data_equivalence(ia[key], ib[key], exact=True), f"step {t}, {key}"
            assert data_equivalence(ia[f"_{key}"], ib[f"_{key}"], exact=True)
        if "episode_metrics" in ib:
            mask = ib["_episode_metrics"]
            np.testing.assert_array_equal(ia["_episode_metrics"], mask)
            ends += int(mask.sum())
            for key in METRIC_KEYS:
                np.testing.assert_array_equal(ia["episode_metrics"][key][mask], ib["episode_metrics"][key][mask])
                np.testing.assert_array_equal(ia["episode_metrics"][f"_{key}"], mask)
    assert ends >= 4


def test_parallel_option_is_bit_identical():
    n, steps = 300, 45
    actions = _actions(steps, n, seed=5)
    plain = _vec(n, {**TERMINATING, "parallel": False})
    assert plain.unwrapped._parallel is None and plain.unwrapped.parallel is False
    serial = _vec_rollout(plain, 2, actions)
    threaded = _vec(n, {**TERMINATING, "parallel": True})
    assert threaded.unwrapped._parallel is not None
    for t, (a, b) in enumerate(zip(serial, _vec_rollout(threaded, 2, actions), strict=True)):
        for x, y in zip(a[:4], b[:4], strict=True):
            assert x is None or np.array_equal(x, y), f"step {t}"
        for key in INFO_KEYS:
            np.testing.assert_array_equal(a[4][key], b[4][key])
        assert ("episode_metrics" in a[4]) == ("episode_metrics" in b[4])
        if "episode_metrics" in a[4]:
            for key in METRIC_KEYS:
                np.testing.assert_array_equal(a[4]["episode_metrics"][key], b[4]["episode_metrics"][key])
    before = threaded.unwrapped._sim.state.copy()
    bad = actions[0].copy()
    bad[250, 1] = np.nan
    with pytest.raises(ValueError, match=r"actions\[250\]"):
        threaded.step(bad)
    np.testing.assert_array_equal(threaded.unwrapped._sim.state, before)


def test_seed_list_and_unseeded_resets_continue_each_envs_generator():
    n = 3
    seeds = [42, 7, 42]
    venv = AUVFollowVectorEnv(num_envs=n, scenario="S2", **SHORT)
    singles = [gym.make("AUVFollow-S2-v0", **SHORT) for _ in range(n)]
    obs, _ = venv.reset(seed=seeds)
    for i in range(n):
        np.testing.assert_array_equal(obs[i], singles[i].reset(seed=seeds[i])[0])
    np.testing.assert_array_equal(obs[0], obs[2])  # same seed, same episode
    for _ in range(3):  # explicit unseeded resets draw the next episode from each env's generator
        obs, _ = venv.reset()
        for i in range(n):
            np.testing.assert_array_equal(obs[i], singles[i].reset()[0])
    obs, _ = venv.reset(seed=[None, 5, None])  # None keeps that env's generator
    np.testing.assert_array_equal(obs[0], singles[0].reset()[0])
    np.testing.assert_array_equal(obs[1], singles[1].reset(seed=5)[0])
    with pytest.raises(ValueError, match="num_envs=3"):
        venv.reset(seed=[1, 2])


def test_reset_mask_resets_only_those_envs():
    n = 3
    venv = AUVFollowVectorEnv(num_envs=n, **SHORT)
    with pytest.raises(ValueError, match="first reset"):
        venv.reset(options={"reset_mask": np.array([True, False, True])})
    venv.reset(seed=0)
    for a in _actions(5, n):
        obs, *_ = venv.step(a)
    mask = np.array([False, True, False])
    obs2, info = venv.reset(seed=20, options={"reset_mask": mask})
    np.testing.assert_array_equal(obs2[[0, 2]], obs[[0, 2]])
    np.testing.assert_array_equal(obs2[1], gym.make(ID, **SHORT).reset(seed=21)[0])
    np.testing.assert_array_equal(info["_tracking_error"], mask)
    assert info["time"][1] == 0.0 and info["time"][0] == pytest.approx(0.25)


@pytest.mark.parametrize("bad, match", [
    ("nan", "NaN or inf"), ("inf", "NaN or inf"), ("shape", "shape"), ("flat", "shape"),
    ("str", "dtype"), ("bool", "dtype"), ("object", "dtype|numeric")])
def test_bad_actions_raise_and_change_nothing(bad, match):
    n = 3
    venv = AUVFollowVectorEnv(num_envs=n, **SHORT)
    twin = AUVFollowVectorEnv(num_envs=n, **SHORT)
    venv.reset(seed=4)
    twin.reset(seed=4)
    good = _actions(2, n)
    venv.step(good[0])
    twin.step(good[0])
    sim = venv.unwrapped._sim
    before = {k: getattr(sim, k).copy() for k in ("state", "k", "proc", "queue", "rs", "obs", "truth", "rew", "term")}
    action = good[1].astype(np.float64)
    if bad == "nan":
        action[1, 2] = np.nan
    elif bad == "inf":
        action[2, 0] = -np.inf
    elif bad == "shape":
        action = action[:, :2]
    elif bad == "flat":
        action = action.ravel()
    elif bad == "str":
        action = np.full((n, 3), "a")
    elif bad == "bool":
        action = np.ones((n, 3), dtype=bool)
    else:
        action = [[object()] * 3] * n
    with pytest.raises(ValueError, match=match):
        venv.step(action)
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(sim, k), v, err_msg=k)
    a, b = venv.step(good[1]), twin.step(good[1])
    assert data_equivalence(a, b, exact=True)


def test_actions_of_envs_being_autoreset_are_ignored_like_sync():
    n = 2
    venv = AUVFollowVectorEnv(num_envs=n, **SHORT)
    venv.reset(seed=0)
    zeros = np.zeros((n, 3))
    for _ in range(40):
        *_, trunc, _ = venv.step(zeros)
    assert trunc.all()
    obs, rew, term, trunc, info = venv.step(np.full((n, 3), np.nan))  # resets: actions unused
    np.testing.assert_array_equal(rew, 0.0)
    assert not term.any() and not trunc.any()
    np.testing.assert_array_equal(info["time"], 0.0)
    for i in range(n):  # the second episode of a single env seeded i
        single = gym.make(ID, **SHORT)
        single.reset(seed=i)
        np.testing.assert_array_equal(obs[i], single.reset()[0])


def test_accepts_other_dtypes_layouts_and_lists():
    n = 2
    a = _actions(1, n)[0]
    ref = AUVFollowVectorEnv(num_envs=n)
    ref.reset(seed=1)
    expected = ref.step(a)
    for variant in (a.astype(np.float64), np.asfortranarray(a), a.tolist(), a[:, ::-1].copy()[:, ::-1]):
        venv = AUVFollowVectorEnv(num_envs=n)
        venv.reset(seed=1)
        assert data_equivalence(venv.step(variant), expected, exact=True)


def test_kernels_get_float64_actions_whatever_the_callers_dtype():
    """One compiled specialisation of the step kernels serves float32 and float64 actions (each
    more dtype compiled the whole step again, seconds at the first step), and the caller's
    array is never written, also when the actions of envs being autoreset are zeroed."""
    n = 2
    venv = AUVFollowVectorEnv(num_envs=n, parallel=False, **SHORT)
    venv.reset(seed=0)
    seen = []
    kernel = venv._kernel

    def spy(*args):
        seen.append(args[-1].dtype)
        return kernel(*args)

    venv._kernel = spy
    a32 = _actions(1, n)[0]
    a64 = a32.astype(np.float64)
    kept32, kept64 = a32.copy(), a64.copy()
    venv.step(a32)
    venv.step(a64)
    for _ in range(38):  # to the end of the 40-step episodes
        *_, trunc, _ = venv.step(a64)
    assert trunc.all()
    venv.step(a64)  # both envs autoreset: their actions are zeroed in a copy
    venv.step(a32)
    assert seen == [np.dtype(np.float64)] * 42
    np.testing.assert_array_equal(a32, kept32)
    np.testing.assert_array_equal(a64, kept64)


def test_spaces_spec_metadata_and_returned_data_not_reused():
    venv = _vec(4, {"disturbance": "L1", **SHORT}, env_id="AUVFollow-v0")
    single = gym.make("AUVFollow-v0", disturbance="L1", **SHORT)
    assert isinstance(venv, AUVFollowVectorEnv)
    assert venv.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
    assert venv.single_action_space == single.action_space
    assert venv.single_observation_space == single.observation_space
    assert venv.action_space.shape == (4, 3) and venv.observation_space.shape == (4, 16)
    assert venv.task_spec == single.unwrapped.task_spec
    assert venv.task_spec.disturbance == "L1" and venv.task_spec.n_steps == 40
    assert venv.spec.id == "AUVFollow-v0" and venv.spec.kwargs["num_envs"] == 4
    obs, info = venv.reset(seed=0)
    assert venv.observation_space.contains(obs)
    snapshot = (obs.copy(), info["tracking_error"].copy())
    out = venv.step(venv.action_space.sample())
    out2 = venv.step(venv.action_space.sample())
    np.testing.assert_array_equal(obs, snapshot[0])
    np.testing.assert_array_equal(info["tracking_error"], snapshot[1])
    assert not np.shares_memory(out[0], out2[0]) and not np.shares_memory(out[1], out2[1])
    assert out[1].dtype == np.float64 and out[2].dtype == np.bool_ and out[3].dtype == np.bool_
    # nor by a reset of some envs, nor a refused step: what a step or reset handed out stays as it was
    kept = {"obs": out2[0], **{key: out2[4][key] for key in ("tracking_error", "true_target", "follower_pose")}}
    before = {key: v.copy() for key, v in kept.items()}
    out2[0][:] = -7.0  # what a caller does with its arrays does not reach the env
    kept["obs"] = out2[0].copy()
    obs_r, info_r = venv.reset(seed=5, options={"reset_mask": np.array([True, False, True, False])})
    np.testing.assert_array_equal(obs_r[[1, 3]], before["obs"][[1, 3]])  # the others keep their last observation
    before["obs"] = kept["obs"]
    assert not np.array_equal(obs_r[[0, 2]], before["obs"][[0, 2]])
    kept.update({"reset obs": obs_r, "reset error": info_r["tracking_error"]})
    before.update({"reset obs": obs_r.copy(), "reset error": info_r["tracking_error"].copy()})
    with pytest.raises(ValueError, match="NaN"):
        venv.step(np.full((4, 3), np.nan))
    venv.step(venv.action_space.sample())
    for key, v in kept.items():
        np.testing.assert_array_equal(v, before[key], err_msg=key)


def test_registered_for_every_id_and_arguments_validated():
    for env_id in auv_follow_env.ENV_IDS:
        assert gym.spec(env_id).vector_entry_point == "auv_follow_env.vector_env:AUVFollowVectorEnv"
        venv = gym.make_vec(env_id, num_envs=2)  # the default mode is the vector entry point
        assert isinstance(venv, AUVFollowVectorEnv)
        venv.close()
    with pytest.raises(ValueError, match="max_episode_steps=1200 disagrees"):
        _vec(2, {"episode_s": 2.0, "steady_start_s": 1.0, "max_episode_steps": 1200})
    with pytest.raises(TypeError, match="unexpected keyword argument 'delay'"):
        _vec(2, {"delay": 1.0})
    with pytest.raises(ValueError, match="render_mode"):
        AUVFollowVectorEnv(num_envs=2, render_mode="rgb_array")
    with pytest.raises(ValueError, match="num_envs"):
        AUVFollowVectorEnv(num_envs=0)
    with pytest.raises(RuntimeError, match="reset"):
        AUVFollowVectorEnv(num_envs=2).step(np.zeros((2, 3)))


def test_gymnasium_vector_wrappers_read_the_infos():
    n = 3
    venv = RecordEpisodeStatistics(_vec(n, SHORT))
    venv.reset(seed=0)
    for a in _actions(41, n):
        _, _, term, trunc, info = venv.step(a)
        if (term | trunc).any():
            assert info["_episode"].all() and np.all(info["episode"]["l"] == 40)
    listed = DictInfoToList(_vec(n, SHORT))
    listed.reset(seed=0)
    for a in _actions(40, n):
        *_, infos = listed.step(a)
    assert len(infos) == n and all(set(METRIC_KEYS) <= set(d["episode_metrics"]) for d in infos)


def test_bench_script_smoke(tmp_path):
    from experiments.bench_vector import main

    out = tmp_path / "bench.md"
    text = main(["--budget", "0.01", "--sizes", "1", "3", "--no-parallel", "--no-cold-start", "--out", str(out)])
    assert out.read_text() == text
    assert "| 3 |" in text and "native, both cores / SyncVectorEnv" in text


def test_parallel_is_chosen_automatically_and_overridable():
    import numba

    threads = numba.get_num_threads()
    assert _vec(255, {}).unwrapped.parallel is False  # small batches stay serial
    assert _vec(256, {}).unwrapped.parallel is (threads > 1)
    assert _vec(4096, {"parallel": False}).unwrapped.parallel is False
    assert _vec(128, {"parallel": True}).unwrapped.parallel is (threads > 1)  # two chunks of 64
    assert _vec(100, {"parallel": True}).unwrapped.parallel is False  # cannot split
    with pytest.raises(ValueError, match="parallel="):
        _vec(8, {"parallel": "yes"})


def test_parallel_kernel_rejects_non_finite_actions_without_changing_anything():
    venv = _vec(300, {"parallel": True})
    venv.reset(seed=0)
    sim = venv.unwrapped._sim
    before = [x.copy() for x in (sim.state, sim.k, sim.proc, sim.obs)]
    a = np.zeros((300, 3), dtype=np.float32)
    a[299, 1] = np.nan
    with pytest.raises(ValueError, match=r"actions\[299\]"):
        venv.step(a)
    for x, y in zip(before, (sim.state, sim.k, sim.proc, sim.obs), strict=True):
        np.testing.assert_array_equal(x, y)


_CACHE_PROBE = """
import numpy as np, gymnasium as gym
import auv_follow_env
from auv_follow_env import dynamics as dyn
venv = gym.make_vec("AUVFollow-S4-v0", num_envs=300, vectorization_mode="vector_entry_point", parallel=True)
venv.reset(seed=0)
venv.step(np.zeros((300, 3), dtype=np.float32))
print(sum(dyn.step_kernel_parallel.stats.cache_hits.values()), len(dyn.step_kernel_parallel.stats.cache_misses))
"""


def test_parallel_kernel_is_cached_on_disk(tmp_path):
    # the threaded kernel is a module-level function, so its disk cache hits
    # in a new process and no further cache files appear
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_NUM_THREADS": "2"}

    def run() -> tuple[list[int], set[str]]:
        out = subprocess.run([sys.executable, "-c", _CACHE_PROBE], capture_output=True, text=True, env=env,
                             check=True)
        files = {str(f.relative_to(tmp_path)) for f in tmp_path.rglob("*step_kernel_parallel*")}
        return [int(x) for x in out.stdout.split()[-2:]], files

    (hits1, _), files1 = run()
    (hits2, misses2), files2 = run()
    assert hits2 >= 1 and misses2 == 0
    assert files1 and files2 == files1


def test_omp_wait_policy_sleeps_only_on_a_busy_machine(monkeypatch):
    from auv_follow_env.vector_env import omp_wait_policy

    for var in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):  # recorded first, so teardown restores them
        monkeypatch.setenv(var, "x")
        monkeypatch.delenv(var)
    assert omp_wait_policy(load=0.9, cpus=2) is None  # a core to spare: libgomp's default
    assert "OMP_WAIT_POLICY" not in __import__("os").environ
    assert omp_wait_policy(load=1.5, cpus=2) == "PASSIVE"  # no core to spare
    assert __import__("os").environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # the user's choice wins
    assert omp_wait_policy(load=9.0, cpus=2) is None
    assert __import__("os").environ["OMP_WAIT_POLICY"] == "ACTIVE"
    monkeypatch.delenv("OMP_WAIT_POLICY")
    monkeypatch.setenv("GOMP_SPINCOUNT", "1000")
    assert omp_wait_policy(load=9.0, cpus=2) is None


def test_error_history_equals_the_per_step_tracking_errors_at_every_step():
    """The kernel stages each env's error samples and writes them 8 at a time: at every step
    (any k, not only multiples of 8) ``errors(i)`` must equal the tracking errors the steps
    reported, and an ended episode's metrics must be those of exactly that series."""
    from auv_follow_env.metrics import tracking_metrics

    n = 6
    venv = AUVFollowVectorEnv(num_envs=n, scenario="S4", episode_s=3.0, steady_start_s=1.0)
    venv.reset(seed=5)
    sim = venv._sim
    rng = np.random.default_rng(2)
    seen = [[] for _ in range(n)]
    ended_checked = 0
    for _ in range(200):
        a = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        a[:2] *= 4.0  # clipped to +-1: envs 0-1 at full thrust, some terminate early
        _, _, term, trunc, info = venv.step(a)
        for i in range(n):
            if not (sim.k[i] == 0):  # (an autoreset step starts a new series)
                seen[i].append(info["tracking_error"][i])
            else:
                seen[i] = []
            errs, times = sim.errors(i)
            np.testing.assert_array_equal(errs, seen[i])
            assert times.shape == errs.shape
            if term[i] or trunc[i]:
                ref = tracking_metrics(np.array(seen[i]), times, venv.config.steady_start_s)
                for key, value in ref.items():
                    got = info["episode_metrics"][key][i]
                    assert got == value or (np.isnan(got) and np.isnan(value)), (i, key)
                ended_checked += 1
    assert ended_checked >= n  # every env ended at least once (3 s episodes, 200 steps)
