"""Speed of the native vector env against SyncVectorEnv, CartPole's native vector env and
the bare physics kernel, in env-steps per second; at the largest N also the policy loop
(``evaluate_batched`` with PROPOSED), a profile of the batched step and the kernel's
operation count against the machine's measured throughput.

    python -m experiments.bench_vector                    # N = 1, 64, 1024, 4096; ~1 s per cell
    python -m experiments.bench_vector --budget 0.2 --sizes 1 64

For each N: (a) ``AUVFollowVectorEnv`` on one thread (``parallel=False``) and (b) on numba's
threads (``parallel=True``), both also with ``sincos="libm"`` (glibc's sin/cos instead of the
default SIMD polynomial), (c) the v1 tier the same ways, (d) ``SyncVectorEnv`` of
the single env (``gym.make_vec(..., "sync")``, with Gymnasium's default wrappers), (e)
``gym.make_vec("CartPole-v1", ..., "vector_entry_point")`` and (f) ``dynamics.integrate``
alone (follower + target RK4, no link, observation, reward or Python; one thread). Actions
are sampled before timing and cycled. Every cell runs a warm-up step (numba compiles once,
cached on disk), then doubles its step count until ``--budget`` seconds have passed (at
least one timed step: a few steps for SyncVectorEnv at N = 4096). The cells of a size are
measured ``--repeats`` times, interleaved, and the best rate is kept (other processes only
ever slow a cell down). Then the cold start: the first ``reset(); step(a)`` of the single env
(and of a 64-env vector env) in a new process with an empty ``NUMBA_CACHE_DIR``, and again with
that cache (:func:`cold_start`). Writes the Markdown table, the profile and the goals to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numba
import numpy as np
from numba import njit

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env import dynamics as dyn
from auv_follow_env.sim import BatchSim
from experiments.outputs import output_path, write_report


@dataclass
class Args:
    env_id: str = "AUVFollow-S4-v0"  #: the AUVFollow id benchmarked
    tier_id: str = "AUVFollow-Hard-v1"  #: the v1 id timed beside it (native, single-threaded)
    sizes: list[int] = field(default_factory=lambda: [1, 64, 256, 1024, 4096])  #: numbers of envs N
    budget: float = 1.0  #: seconds of timed stepping per cell (after one warm-up step)
    max_sync_envs: int = 4096  #: skip SyncVectorEnv above this N (building it is slow)
    out: Path = Path("results/bench_vector.md")  #: Markdown output
    seed: int = 0  #: seed of the envs and of the pre-sampled actions
    parallel: bool = True  #: also time the native envs with parallel=True (numba threads)
    repeats: int = 3  #: interleaved repetitions of each size's cells (best kept)
    policy: bool = True  #: time evaluate_batched with PROPOSED at the largest N
    policy_episode_s: float = 60.0  #: episode length of that run [s]
    cold_start: bool = True  #: time the first reset + step of a fresh process with an empty numba cache
    burn: int = 1200  #: steady state: control steps stepped before timing (0: not measured)


#: goals at the largest N: (label, numerator column, denominator column, minimum ratio)
GOALS = (("native, both cores / SyncVectorEnv", "parallel", "sync", 50.0),
         ("native / bare kernel, one thread (>= 0.67 means env step <= 1.5x kernel)", "native", "kernel", 1 / 1.5),
         ("v1 tier native / v0 native, one thread", "tier", "native", 0.9),
         ("evaluate_batched with PROPOSED / native env alone, both cores", "policy", "parallel", 0.7))
#: absolute goals at the largest N: (label, column, minimum env-steps/s)
RATE_GOALS = (("native, parallel=True (both cores)", "parallel", 3e6), ("native, one thread", "native", 1.8e6))
KERNEL_GOAL_NS = 250.0  #: bare kernel, ns per env-step on one core
COLUMNS = {"native": "AUVFollow native (1 thread)", "parallel": "AUVFollow native, parallel=True",
           "libm": "native, sincos='libm' (1 thread)", "libm_parallel": "native, sincos='libm', parallel=True",
           "tier": "v1 tier native (1 thread)", "tier_parallel": "v1 tier native, parallel=True",
           "tier_libm_parallel": "v1 tier, sincos='libm', parallel=True",
           "sync": "AUVFollow SyncVectorEnv", "cartpole": "CartPole-v1 native",
           "kernel": "bare kernel (integrate, 1 thread)", "kernel_libm": "bare kernel, libm"}
#: the same goals with sincos="libm" (glibc's sin/cos, the 0.1.0 default)
LIBM_OF = {"native": "libm", "parallel": "libm_parallel", "tier_parallel": "tier_libm_parallel",
           "policy": "policy_libm", "kernel": "kernel_libm"}
COLD_GOAL_S, CACHED_GOAL_S = 15.0, 1.0  #: first reset + step of a fresh clone / with the numba cache [s]


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-id", default=Args.env_id, help="AUVFollow id (default %(default)s)")
    p.add_argument("--tier-id", default=Args.tier_id, help="v1 id timed beside it (default %(default)s)")
    p.add_argument("--sizes", type=int, nargs="+", default=Args().sizes, help="numbers of envs")
    p.add_argument("--budget", type=float, default=Args.budget, help="timed seconds per cell")
    p.add_argument("--max-sync-envs", type=int, default=Args.max_sync_envs,
                   help="largest N for SyncVectorEnv (default %(default)s)")
    p.add_argument("--out", type=Path, default=None,
                   help="Markdown output file (default: results/bench_vector.md; results/tmp/ with non-default "
                        "settings)")
    p.add_argument("--seed", type=int, default=Args.seed, help="seed of envs and actions")
    p.add_argument("--no-parallel", dest="parallel", action="store_false",
                   help="skip the parallel=True columns (numba threads)")
    p.add_argument("--repeats", type=int, default=Args.repeats, help="interleaved repeats (default %(default)s)")
    p.add_argument("--no-policy", dest="policy", action="store_false",
                   help="skip the evaluate_batched (PROPOSED) run")
    p.add_argument("--policy-episode-s", type=float, default=Args.policy_episode_s,
                   help="episode length of the evaluate_batched run [s] (default %(default)s)")
    p.add_argument("--no-cold-start", dest="cold_start", action="store_false",
                   help="skip the cold-start measurement (a fresh process compiling the kernels, about a minute)")
    p.add_argument("--burn", type=int, default=Args.burn,
                   help="steady state: control steps before timing the native envs again at the largest N, so that "
                        "episodes end and restart at their long-run rate (default %(default)s, one episode; 0: skip)")
    a = p.parse_args(argv)
    if a.budget <= 0 or any(n < 1 for n in a.sizes) or a.repeats < 1 or a.policy_episode_s <= 0 or a.burn < 0:
        p.error("--budget and --policy-episode-s must be > 0, --sizes and --repeats >= 1, --burn >= 0")
    a.out = output_path(a, p, Args.out)
    return Args(**vars(a))


def rate(step: Callable[[int], object], n_envs: int, budget: float) -> float:
    """Env-steps per second of ``step(j)`` (j = step counter), doubling the count until ``budget`` s."""
    step(0)  # warm-up (compilation, lazy allocation)
    count, j = 1, 1
    while True:
        t0 = time.perf_counter()
        for _ in range(count):
            step(j)
            j += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= budget:
            return count * n_envs / elapsed
        count = max(count * 2, int(count * 1.2 * budget / max(elapsed, 1e-9)))


#: the cold-start probe: import, make, reset, one step (the first step of a newcomer), timed inside
#: the fresh process (interpreter start-up excluded); argv: env id, number of envs (0: gym.make)
_COLD_PROBE = """
import sys, time
t0, c0 = time.perf_counter(), time.process_time()
import gymnasium as gym, numpy as np
import auv_follow_env
env_id, n = sys.argv[1], int(sys.argv[2])
t1, c1 = time.perf_counter(), time.process_time()
if n == 0:
    env = gym.make(env_id)
    env.reset(seed=0)
    env.step(np.zeros(3, dtype=np.float32))
else:
    env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    env.step(np.zeros((n, 3), dtype=np.float32))
t2, c2 = time.perf_counter(), time.process_time()
print(t1 - t0, t2 - t1, c2 - c1)
"""


def cold_start(env_id: str, num_envs: int = 0, root: Path | None = None) -> dict[str, float]:
    """Seconds of the first ``reset(); step(a)`` in a new process with an empty numba cache
    (``NUMBA_CACHE_DIR`` a fresh temporary directory: what a fresh clone pays), then again in a
    second new process with that cache (the cached start); imports timed apart; ``*_cpu``: the
    process's CPU time for the reset and step (less sensitive than wall time to other processes
    sharing the cores). ``num_envs`` 0:
    the single env through ``gym.make``; else the native vector env of that size. ``root``: the
    source tree to import (default this checkout)."""
    import subprocess
    import sys
    import tempfile

    out = {}
    root = Path(__file__).resolve().parent.parent if root is None else Path(root)
    with tempfile.TemporaryDirectory(prefix="numba-cold-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(root)}
        for label in ("cold", "cached"):
            res = subprocess.run([sys.executable, "-c", _COLD_PROBE, env_id, str(num_envs)], cwd=root, env=env,
                                 capture_output=True, text=True, check=True)
            imp, first, cpu = map(float, res.stdout.split())
            out[label], out[label + "_import"], out[label + "_cpu"] = first, imp, cpu
    return out


def _cycle(batches: np.ndarray) -> Callable[[int], np.ndarray]:
    k = len(batches)
    return lambda j: batches[j % k]


def _native(env_id: str, n: int, seed: int, parallel: bool, sincos: str = "simd"):
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", parallel=parallel,
                        sincos=sincos)
    venv.reset(seed=seed)
    return venv


def bench_size(args: Args, n: int, rng: np.random.Generator) -> dict[str, float]:
    """One row: env-steps/s of each method at N = n (best of ``args.repeats`` interleaved runs)."""
    k = 8  # distinct pre-sampled action batches, cycled
    acts = rng.uniform(-1.0, 1.0, (k, n, 3)).astype(np.float32)
    act = _cycle(acts)
    cacts = _cycle(rng.integers(0, 2, (k, n)))
    envs = {"native": _native(args.env_id, n, args.seed, False),
            "libm": _native(args.env_id, n, args.seed, False, "libm"),
            "tier": _native(args.tier_id, n, args.seed, False)}
    if args.parallel:
        envs["parallel"] = _native(args.env_id, n, args.seed, True)
        envs["libm_parallel"] = _native(args.env_id, n, args.seed, True, "libm")
        envs["tier_parallel"] = _native(args.tier_id, n, args.seed, True)
        envs["tier_libm_parallel"] = _native(args.tier_id, n, args.seed, True, "libm")
    if n <= args.max_sync_envs:
        envs["sync"] = gym.make_vec(args.env_id, num_envs=n, vectorization_mode="sync")
        envs["sync"].reset(seed=args.seed)
    envs["cartpole"] = gym.make_vec("CartPole-v1", num_envs=n, vectorization_mode="vector_entry_point")
    envs["cartpole"].reset(seed=args.seed)
    config = envs["native"].unwrapped.config
    sim = BatchSim(config, n)
    sim.reset(np.arange(n), [np.random.default_rng(args.seed + i) for i in range(n)])
    forces = _cycle(acts.astype(np.float64) * np.asarray(config.force_limits))
    t0 = np.zeros(n)
    steps: dict[str, Callable[[int], object]] = {
        name: ((lambda j, e=e: e.step(cacts(j))) if name == "cartpole" else (lambda j, e=e: e.step(act(j))))
        for name, e in envs.items()}
    steps["kernel"] = lambda j: dyn.integrate(sim.state, sim.params, sim.cfg, t0, forces(j), True)
    steps["kernel_libm"] = lambda j: dyn.integrate(sim.state, sim.params, sim.cfg, t0, forces(j), False)
    row = {c: float("nan") for c in COLUMNS}
    for _ in range(args.repeats):
        for name, step in steps.items():
            r = rate(step, n, args.budget)
            row[name] = r if not np.isfinite(row[name]) else max(row[name], r)
    for e in envs.values():
        e.close()
    return row


def steady_state(args: Args, n: int) -> tuple[dict[str, float], dict[str, tuple[float, float, float]]]:
    """Env-steps/s of the native envs at N = n after ``args.burn`` control steps of random actions:
    right after a reset no episode has ended yet, while a long run (training, Monte Carlo) restarts
    about one env in (episode length) per step; each env's reset (its parameters and the
    target's and link's warm-up) is part of the rate. Returns (rates, columns as
    :func:`bench_size`'s; resets: per single-threaded column, the episode ends per env-step in the
    timed steps, the warm-up steps of each episode and the steps of a full episode)."""
    acts = _cycle(np.random.default_rng(args.seed).uniform(-1.0, 1.0, (8, n, 3)).astype(np.float32))
    cases = {"native": (args.env_id, False), "tier": (args.tier_id, False)}
    if args.parallel:
        cases.update({"parallel": (args.env_id, True), "tier_parallel": (args.tier_id, True)})
    out, resets = {}, {}
    for name, (env_id, par) in cases.items():
        env = _native(env_id, n, args.seed, par)
        for j in range(args.burn):
            env.step(acts(j))
        ends = [0, 0]  # episode ends, env-steps stepped

        def step(j: int, e=env, ends=ends) -> None:
            res = e.step(acts(j))
            ends[0] += int(np.count_nonzero(res[2] | res[3]))
            ends[1] += n

        out[name] = max(rate(step, n, args.budget) for _ in range(args.repeats))
        if not par:  # each reset simulates the episode's warm-up (target, link, processes)
            cfg = env.unwrapped._sim.cfg
            resets[name] = (ends[0] / ends[1], float(cfg[dyn.C_WARM]), float(cfg[dyn.C_NSTEPS]))
        env.close()
    return out, resets


# --- profile of the batched step ------------------------------------------------------------
@njit(cache=True, _nrt=False)
def _refresh_all(state, k, proc, p, cfg, reps):
    """refresh_trig for every env with its keys invalidated: the libm values of a new step."""
    for _ in range(reps):
        for i in range(state.shape[0]):
            proc[i, dyn.R_TK] = np.nan
            proc[i, dyn.R_PSK] = np.nan
            proc[i, dyn.R_PTK] = np.nan
            dyn.refresh_trig(state, k, proc, p, cfg, i)


@njit(cache=True, _nrt=False)
def _refresh_block_all(state, k, proc, p, cfg, reps, fast, wk):
    """refresh_trig_block over the batch (as step_range runs it; ``fast``: the default's SIMD sin/cos)."""
    n = state.shape[0]
    for _ in range(reps):
        for a in range(0, n, dyn.BLOCK):
            m = min(dyn.BLOCK, n - a)
            dyn.gather_block(state, p, a, m, wk)
            dyn.refresh_trig_block(k, proc, cfg, a, m, wk, fast)


@njit(cache=True, _nrt=False)
def _observe_all(state, k, proc, p, cfg, obs, truth, reps, wk):
    """The observation, truth and error of every env (libm values cached), block by block as the
    step computes them (the relative heading's sin/cos for a block at once): idempotent."""
    n = state.shape[0]
    fast = cfg[dyn.C_FAST] != 0.0
    B = dyn.BLOCK
    for _ in range(reps):
        for a in range(0, n, B):
            m = min(B, n - a)
            for b in range(m):
                wk[dyn.K_DP * B + b] = proc[a + b, dyn.R_HX + 2] - state[a + b, 2]
            dyn._sincos_rows(wk, dyn.K_DP, dyn.K_DPS, dyn.K_DPC, m, fast)
            for b in range(m):
                dyn._observe_dp(state, k, proc, p, cfg, a + b, obs, truth, wk[dyn.K_DPC * B + b],
                                wk[dyn.K_DPS * B + b])


@njit(cache=True, _nrt=False)
def _link_all(state, k, proc, queue, rs, p, cfg, reps):
    """The link of every env at reps successive control steps (sends when due, arrivals)."""
    for r in range(reps):
        for i in range(state.shape[0]):
            dyn.link_tick(state, proc, queue, rs, p, cfg, i, k[i] + r)


@njit(cache=True, _nrt=False)
def _advance_cached(state, k, proc, p, cfg, forces, reps, wk):
    """The block RK4 of the step from the cached start values (as step_range runs it)."""
    n = state.shape[0]
    for _ in range(reps):
        for a in range(0, n, dyn.BLOCK):
            m = min(dyn.BLOCK, n - a)
            dyn.gather_block(state, p, a, m, wk)
            for b in range(m):
                i = a + b
                for c in range(3):
                    wk[dyn.K_F * dyn.BLOCK + c * dyn.BLOCK + b] = forces[i, c]
                for j in range(10):
                    wk[(dyn.K_S + j) * dyn.BLOCK + b] = proc[i, dyn.R_TS + j]
                    wk[(dyn.K_C + j) * dyn.BLOCK + b] = proc[i, dyn.R_TC + j]
                wk[dyn.K_C0 * dyn.BLOCK + b] = proc[i, dyn.R_PSC]
                wk[dyn.K_S0 * dyn.BLOCK + b] = proc[i, dyn.R_PSS]
                wk[dyn.K_CT * dyn.BLOCK + b] = proc[i, dyn.R_PTC]
                wk[dyn.K_STT * dyn.BLOCK + b] = proc[i, dyn.R_PTS]
                wk[dyn.K_T0 * dyn.BLOCK + b] = k[i] * cfg[dyn.C_DT]
            # (the state is not written back)
            dyn.advance_block(wk, cfg[dyn.C_DT], int(cfg[dyn.C_NSUB]), m, cfg[dyn.C_FAST] != 0.0)


def _ns_per_env(f: Callable[[int], object], n: int, reps: int, budget: float, repeats: int) -> float:
    """Best ns per env of f(reps) (one call covers reps passes over n envs)."""
    f(1)
    best = math.inf
    for _ in range(repeats):
        count, t = 1, 0.0
        while t < budget / 4:
            t0 = time.perf_counter()
            f(reps * count)
            t = time.perf_counter() - t0
            count *= 2
        best = min(best, t / (reps * count // 2) / n * 1e9)
    return best


def profile(args: Args, n: int, env_id: str | None = None) -> dict[str, float]:
    """ns per env-step of the parts of one batched step of ``env_id`` (default ``args.env_id``)
    at N = n, on one thread."""
    venv = _native(env_id or args.env_id, n, args.seed, False)
    rng = np.random.default_rng(args.seed)
    acts = rng.uniform(-1.0, 1.0, (8, n, 3)).astype(np.float32) * 0.2  # mild: few episode ends
    for j in range(20):
        venv.step(acts[j % 8])
    sim = venv.unwrapped._sim
    kern, kargs = sim.step_call()
    flat = [a.reshape(-1).astype(np.float64) for a in acts]  # (as the env hands them to its kernel)
    forces = acts[0].astype(np.float64) * np.asarray(sim.config.force_limits)
    t0 = np.zeros(n)
    state = sim.state.copy()
    out: dict[str, float] = {}
    rp, b = args.repeats, args.budget
    wk = dyn.new_work_buffer(True)  # (the helpers below, like the step, allocate nothing)
    out["env_step"] = _ns_per_env(lambda r: [venv.step(acts[j % 8]) for j in range(r)], n, 1, b, rp)
    out["step_kernel"] = _ns_per_env(lambda r: [kern(*kargs, flat[j % 8]) for j in range(r)], n, 1, b, rp)
    out["integrate"] = _ns_per_env(lambda r: [dyn.integrate(state, sim.params, sim.cfg, t0, forces)
                                              for _ in range(r)], n, 1, b, rp)
    out["advance"] = _ns_per_env(lambda r: _advance_cached(sim.state, sim.k, sim.proc, sim.params, sim.cfg,
                                                           forces, r, wk), n, 1, b, rp)
    out["libm"] = _ns_per_env(lambda r: _refresh_all(sim.state, sim.k, sim.proc, sim.params, sim.cfg, r),
                              n, 1, b, rp)
    out["libm_block"] = _ns_per_env(lambda r: _refresh_block_all(sim.state, sim.k, sim.proc, sim.params, sim.cfg,
                                                                 r, False, wk), n, 1, b, rp)
    out["fast_block"] = _ns_per_env(lambda r: _refresh_block_all(sim.state, sim.k, sim.proc, sim.params, sim.cfg,
                                                                 r, True, wk), n, 1, b, rp)
    obs, truth = sim.obs.copy(), sim.truth.copy()
    out["observe"] = _ns_per_env(lambda r: _observe_all(sim.state, sim.k, sim.proc, sim.params, sim.cfg, obs,
                                                        truth, r, wk), n, 1, b, rp)
    proc, queue, rs = sim.proc.copy(), sim.queue.copy(), sim.rs.copy()
    out["link"] = _ns_per_env(lambda r: _link_all(sim.state, sim.k, proc, queue, rs, sim.params, sim.cfg, r),
                              n, 1, b, rp)
    fast = sim.cfg[dyn.C_FAST] != 0.0
    out["processes"] = _ns_per_env(lambda r: dyn.update_processes_all(proc, rs, sim.params, r, fast), n, 1, b, rp)
    venv.close()
    return out


# --- operation count and machine throughput -------------------------------------------------
def op_count(nsub: int) -> dict[str, dict[str, int]]:
    """Floating-point operations and libm calls per env-step (v0 settings), counted from the
    source of :mod:`auv_follow_env.dynamics` (a small-angle cos/sin pair = 35 flops of which
    11 divisions; an RHS evaluation 31 flops, 3 divisions; a tone rotation 6 flops)."""
    taylor, taylor_div = 35, 11
    per_sub = (2 * 10 * 6 + 2 * 20  # two half-substep rotations of ten tones, two forcings
               + 4 * 31 + 3 * 6 + 3 + 6 * (taylor + 6) + 9 * 6 + 4)  # RK4 stages, turns, combination
    div_sub = 4 * 3 + 6 * taylor_div + 1
    # arguments; each tone's rotation-factor key compared (a product, two compares); the factors
    # recomputed for the two current tones only (their periods are drawn per episode; the other
    # eight frequencies are constants of the config, reused from the previous block)
    fresh = 2
    tones = 10 * 2 + 10 * 3 + fresh * (taylor + 1)
    kernel = {"flops": tones + nsub * per_sub, "divisions": fresh * taylor_div + nsub * div_sub,
              "libm": 20 + 4 * nsub}
    step = {"flops": kernel["flops"] + 80, "divisions": kernel["divisions"] + 1,
            "libm": 20 + 4 * (nsub - 1) + 4 + 2}  # tones, headings (cached at the step's start), psd - psi
    return {"kernel": kernel, "step": step}


@njit(cache=True)
def _libm_loop(x, out, reps):
    for _ in range(reps):
        for i in range(x.shape[0]):
            out[i] = math.sin(x[i]) + math.cos(x[i])


@njit(cache=True, error_model="numpy")
def _fast_loop(x, out, reps):
    for _ in range(reps):
        for i in range(x.shape[0]):
            sv, cv = dyn.fast_sincos(x[i])
            out[i] = sv + cv


@njit(cache=True, error_model="numpy")
def _flop_loop(x, out, reps):
    for _ in range(reps):
        for i in range(x.shape[0]):  # 16 flops, vectorised
            v = x[i]
            out[i] = ((((((((v * 0.5 + 1.0) * v + 0.25) * v - 0.5) * v + 0.75) * v - 1.5) * v + 2.0) * v - 0.1)
                      * v + 0.3)


@njit(cache=True, error_model="numpy")
def _div_loop(x, out, reps):
    for _ in range(reps):
        for i in range(x.shape[0]):  # 8 independent divisions, vectorised
            v = x[i]
            out[i] = (v / 3.0 + v / 5.0) + (v / 7.0 + v / 11.0) + (v / 13.0 + v / 17.0) + (v / 19.0 + v / 23.0)


def machine_throughput(budget: float, repeats: int) -> dict[str, float]:
    """Measured on one core: ns per libm sin or cos (glibc; arguments in [-4, 70], as the step's:
    headings and tone phases up to a minute), the same with the default's SIMD fast_sincos, ns
    per SIMD flop (mul/add, L1-resident) and ns per SIMD division."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-4.0, 70.0, 1024)
    out = np.empty_like(x)
    ns_libm = _ns_per_env(lambda r: _libm_loop(x, out, r), 2 * x.size, 50, budget, repeats)
    ns_fast = _ns_per_env(lambda r: _fast_loop(x, out, r), 2 * x.size, 500, budget, repeats)
    ns_flop = _ns_per_env(lambda r: _flop_loop(x, out, r), 18 * x.size, 500, budget, repeats)
    ns_div = _ns_per_env(lambda r: _div_loop(x, out, r), 8 * x.size, 500, budget, repeats)
    return {"libm_ns": ns_libm, "fast_ns": ns_fast, "flop_ns": ns_flop, "div_ns": ns_div}


def limit_ns(ops: dict[str, int], m: dict[str, float], fast: bool = False) -> float:
    """Lower bound of ns per env-step on one core from the op count and the throughputs
    (``fast``: the sin/cos at the SIMD polynomial's cost)."""
    return (ops["libm"] * m["fast_ns" if fast else "libm_ns"] + (ops["flops"] - ops["divisions"]) * m["flop_ns"]
            + ops["divisions"] * m["div_ns"])


def bench_policy(args: Args, n: int, sincos: str = "simd") -> float:
    """env-steps/s of evaluate_batched with PROPOSED in the loop, n episodes (parallel chosen
    automatically), including env creation and the metrics."""
    from controllers import make_controller
    from controllers.evaluation import evaluate_batched

    kw = {"episode_s": args.policy_episode_s, "steady_start_s": min(10.0, args.policy_episode_s / 2),
          "sincos": sincos}
    spec = auv_follow_env.make_task_spec(args.env_id.split("-")[1],
                                         **{k: v for k, v in kw.items() if k != "sincos"})
    evaluate_batched([make_controller("PROPOSED", spec)], args.env_id, seeds=range(8), env_kwargs=kw,
                     progress=False)  # warm-up
    best = 0.0
    for _ in range(max(1, args.repeats - 1)):
        t0 = time.perf_counter()
        df = evaluate_batched([make_controller("PROPOSED", spec)], args.env_id, seeds=range(n), env_kwargs=kw,
                              progress=False)
        best = max(best, float(df["steps"].sum()) / (time.perf_counter() - t0))
    return best


def fmt(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x / 1e6:.2f} M" if x >= 1e6 else f"{x / 1e3:.1f} k"


def report(args: Args, rows: dict[int, dict[str, float]], load: str, load_after: str,
           prof: dict[str, float] | None, machine: dict[str, float], policy: float,
           policy_libm: float = float("nan"), cold: dict[str, dict[str, float]] | None = None,
           tier_prof: dict[str, float] | None = None, steady: dict[str, float] | None = None,
           resets: dict[str, tuple[float, float, float]] | None = None) -> str:
    threads = numba.get_num_threads()
    lines = [f"# Vector env speed: {args.env_id} (and {args.tier_id}), env-steps/s", "",
             f"Machine: {platform.processor() or platform.machine()} ({_cpu_target()}), {os.cpu_count()} CPUs, Python "
             f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, gymnasium "
             f"{gym.__version__}; {args.budget} s per cell after a warm-up step, best of {args.repeats} "
             f"interleaved repeats; load average (1, 5, 15 min) before the run {load}, after it {load_after} "
             f"(other processes share the cores: every figure is a lower bound of what an idle machine gives); "
             f"parallel=True columns on {threads} numba threads, OpenMP wait policy "
             f"{os.environ.get('OMP_WAIT_POLICY', 'libgomp default (brief spin)')} "
             f"(auv_follow_env.vector_env.omp_wait_policy: PASSIVE when the machine was busy at the first threaded "
             f"step).", "",
             "| N | " + " | ".join(COLUMNS.values()) + " | native us/env-step |",
             "|---|" + "---|" * (len(COLUMNS) + 1)]
    for n, row in rows.items():
        lines.append(f"| {n} | " + " | ".join(fmt(row[c]) for c in COLUMNS)
                     + f" | {1e6 / row['native']:.3f} |")
    n = max(rows)
    row = {**rows[n], "policy": policy, "policy_libm": policy_libm}
    lines += ["", f"Goals at N = {n} (default: sincos='simd', SIMD polynomial sin/cos; in brackets the same with "
              f"sincos='libm', glibc's scalar sin/cos, whose results are within 1e-12 of the default's, "
              f"tests/test_fast_math.py):", ""]
    for label, a, b, goal in GOALS:
        r = row[a] / row[b]
        verdict = "met" if r >= goal else ("n/a" if not np.isfinite(r) else "MISSED")
        lines.append(f"- {label}: {r:.2f} (goal >= {goal:.2f}): {verdict}")
    def verdict(r: float, goal: float) -> str:
        return "n/a" if not np.isfinite(r) else ("met" if r >= goal else f"MISSED by {100 * (1 - r / goal):.0f} %")

    for label, col, goal in RATE_GOALS:
        r = row.get(col, float("nan"))
        rf = row.get(LIBM_OF.get(col, ""), float("nan"))
        lines.append(f"- {label}: {fmt(r)} env-steps/s (goal >= {fmt(goal)}): {verdict(r, goal)} "
                     f"[libm: {fmt(rf)}, {verdict(rf, goal)}]")
    if steady:
        r = steady["tier"] / steady["native"]
        lines.append(f"- steady state (after {args.burn} steps: episodes restart at their long-run rate), one "
                     f"thread: {args.env_id} {fmt(steady['native'])}, {args.tier_id} {fmt(steady['tier'])}, ratio "
                     f"{r:.2f} (goal >= 0.90): {verdict(r, 0.9)}; one thread >= 1.8M: "
                     f"{verdict(steady['native'], 1.8e6)}"
                     + (f"; both cores {fmt(steady['parallel'])} (goal >= 3M: {verdict(steady['parallel'], 3e6)}), "
                        f"{args.tier_id} {fmt(steady['tier_parallel'])}" if "parallel" in steady else ""))
        if resets:
            lines.append("  (resets: each episode starts with a warm-up of the target, the link and the processes; "
                         "in the timed steps (random actions) "
                         + "; ".join(f"{eid} {1000 * ends:.2f} episode ends per 1,000 env-steps x "
                                     f"{warm:.0f} warm-up steps = {100 * ends * warm:.1f} % more simulated steps "
                                     f"({100 * warm / length:.0f} % with full {length:.0f}-step episodes)"
                                     for eid, (ends, warm, length) in ((args.env_id, resets["native"]),
                                                                       (args.tier_id, resets["tier"])))
                         + ")")
            # the same rates counting each reset's warm-up steps as simulated steps: what is left of
            # the ratio is the step itself, not the episode's definition (the tier's longer warm-up)
            sim_rate = {name: steady[name] * (1.0 + resets[name][0] * resets[name][1]) for name in ("native", "tier")}
            lines.append(f"  (per simulated step, warm-up steps counted: {args.env_id} {fmt(sim_rate['native'])}, "
                         f"{args.tier_id} {fmt(sim_rate['tier'])}, ratio {sim_rate['tier'] / sim_rate['native']:.2f})")
    if prof:  # why the env step cannot come within 1.5x of the bare kernel: its own parts alone
        parts = {"RK4": prof["advance"], "sin/cos": prof["fast_block"], "observation": prof["observe"],
                 "link": prof["link"], "processes": prof["processes"]}
        lines.append(f"  (the step's own parts, each timed alone in the profile below, add up to "
                     f"{sum(parts.values()):.0f} ns per env-step ("
                     + ", ".join(f"{name} {v:.0f}" for name, v in parts.items())
                     + f"), against 1.5x the bare kernel = {1.5e9 / row['kernel']:.0f} ns: the RK4 and sin/cos are "
                       "the bare kernel's own work, the rest is the task's)")
    kns = 1e9 / row["kernel"]
    kls = 1e9 / row["kernel_libm"]

    def kverdict(x: float) -> str:
        return "met" if x <= KERNEL_GOAL_NS else f"MISSED by {100 * (x / KERNEL_GOAL_NS - 1):.0f} %"

    lines.append(f"- bare kernel: {kns:.0f} ns per env-step on one core (goal <= {KERNEL_GOAL_NS:.0f}): "
                 f"{kverdict(kns)} [libm: {kls:.0f} ns, {kverdict(kls)}]")
    if cold is not None:
        c = cold["single"]

        def sverdict(x: float, goal: float) -> str:
            return "met" if x <= goal else f"MISSED by {100 * (x / goal - 1):.0f} %"

        lines.append(f"- cold start, single env (`gym.make(...)`, first `reset(); step(a)` in a new process with an "
                     f"empty numba cache, import excluded): {c['cold']:.1f} s wall, {c['cold_cpu']:.1f} s CPU "
                     f"(goal <= {COLD_GOAL_S:.0f} s): "
                     f"{sverdict(c['cold'], COLD_GOAL_S)}; the same with the cache (what a fresh clone has after "
                     f"the README's set-up, which runs `python -m auv_follow_env.warm`): {c['cached']:.2f} s (goal <= "
                     f"{CACHED_GOAL_S:.0f} s): {sverdict(c['cached'], CACHED_GOAL_S)}; import {c['cold_import']:.1f} s "
                     f"/ {c['cached_import']:.1f} s")
        if "vector" in cold:
            v = cold["vector"]
            lines.append(f"  (native vector env, N = 64, one thread: {v['cold']:.1f} s cold, {v['cached']:.2f} s "
                         f"cached)")
    if np.isfinite(policy):
        lines.append(f"  (evaluate_batched: {n} episodes of {args.policy_episode_s:g} s, PROPOSED, env creation, "
                     f"reset and metrics included)")
    nsub = _nsub(args.env_id)
    ops = op_count(nsub)
    lines += ["", "## Operation count and the machine's limit", "",
              f"Per env-step (v0, {nsub} RK4 substeps), counted from the kernel's "
              f"source (`op_count`):", "",
              "| | flops | of which divisions | sin/cos calls | limit on one core (ns) | measured (ns) | "
              "fraction of the limit | limit with libm (ns) | measured with libm (ns) | fraction |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    meas = {"kernel": (kns, kls), "step": (1e9 / row["native"], 1e9 / row["libm"])}
    for key, label in (("kernel", "bare kernel (integrate)"), ("step", "native env step (1 thread)")):
        o = ops[key]
        lim, limf = limit_ns(o, machine, True), limit_ns(o, machine)
        m0, m1 = meas[key]
        lines.append(f"| {label} | {o['flops']} | {o['divisions']} | {o['libm']} | {lim:.0f} | {m0:.0f} | "
                     f"{lim / m0:.2f} | {limf:.0f} | {m1:.0f} | {limf / m1:.2f} |")
    floor = ops["step"]["libm"] * machine["libm_ns"]
    floor_simd = ops["step"]["libm"] * machine["fast_ns"]
    lines += ["", f"Measured throughput of one core (same run): glibc sin or cos {machine['libm_ns']:.1f} ns per "
              f"call (arguments in [-4, 70] like the step's; scalar calls), the default's SIMD `fast_sincos` "
              f"{machine['fast_ns']:.1f} ns per value, {1 / machine['flop_ns']:.1f} SIMD flops/ns, "
              f"{1 / machine['div_ns']:.2f} SIMD divisions/ns. The limit is sin/cos calls x their cost + flops / "
              f"SIMD rate: what this arithmetic costs with every vector unit busy and nothing else (no memory, "
              f"no branches, no Python).", "",
              f"**sin/cos:** the {ops['step']['libm']} sin/cos of a step cost {floor_simd:.0f} ns per env-step on one "
              f"core with the default SIMD polynomial, {floor:.0f} ns with glibc's scalar calls (`sincos='libm'`, "
              f"at most {fmt(1e9 / floor)} env-steps/s per core before any other work). The two differ in the last "
              f"bit of about 3 % of the values; since 0.2.0 the v0 contract is a tolerance (1e-9 relative of the "
              f"golden arrays, tests/test_frozen_v0.py), so the faster one is the default. {_footprint(rows)}"]
    if prof is not None:
        p = prof
        tp = tier_prof or {}
        lines += ["", f"## Profile of one batched step (N = {n}, one thread, ns per env-step)", "",
                  "Each part timed alone in a loop over the batch (the link at successive steps, so it sends "
                  "when due); \"rest\" is the kernel's time minus the parts (it can come out below zero: "
                  "the parts, each timed alone, can add up to more than the whole step).", "",
                  f"| part | {args.env_id} ns | share | {args.tier_id} ns | share |", "|---|---|---|---|---|"]
        parts = (("RK4 of follower and target (structure-of-arrays blocks, start values cached)", "advance"),
                 ("sin/cos of the new step (ten tones, both headings: `refresh_trig_block`, SIMD)", "fast_block"),
                 ("observation, truth and error (`_observe_dp`, with the cached values)", "observe"),
                 ("link: send when due, arrivals (`link_tick`)", "link"),
                 ("random processes: the step's draws (`update_processes_block`)", "processes"),
                 ("rest of `step_kernel`: thrusters, reward, termination, gathers, loops", "rest"),
                 ("Python shell: validation, copies, info dict, autoreset (env step - `step_kernel`)", "shell"))
        for q in (p, tp):
            if q:
                q["rest"] = q["step_kernel"] - sum(q[k] for k in ("advance", "fast_block", "observe", "link",
                                                                   "processes"))
                q["shell"] = q["env_step"] - q["step_kernel"]

        def cell(q: dict[str, float], key: str) -> str:
            return f"{q[key]:.0f} | {100 * q[key] / q['env_step']:.0f} %" if q else "- | -"

        for label, key in parts:
            lines.append(f"| {label} | {cell(p, key)} | {cell(tp, key)} |")
        lines.append(f"| **env step** (`venv.step`) | **{p['env_step']:.0f}** | 100 % | "
                     + (f"**{tp['env_step']:.0f}** | 100 % |" if tp else "- | - |"))
        lines += ["", f"The same values with glibc (`refresh_trig_block` with libm, `sincos='libm'`): "
                  f"{p['libm_block']:.0f} ns instead of {p['fast_block']:.0f} ns (per env, the scalar "
                  f"`refresh_trig`: {p['libm']:.0f} ns)."]
        lines += ["", f"For comparison: the bare kernel (`integrate`, which also evaluates its own 28 libm "
                  f"values) {p['integrate']:.0f} ns."]
    return "\n".join(lines) + "\n"


def _footprint(rows: dict[int, dict[str, float]]) -> str:
    """What the table says about the per-env rows (params, processes, packet queue, observation,
    truth, error staging: about 1.7 KB per env in v0) outgrowing the core's L2 cache (512 KB)."""
    small = [n for n in rows if 64 <= n <= 256]
    big = max(rows)
    if not small or big < 1024:
        return ""
    s = max(small)
    r1 = rows[big]["native"] / rows[s]["native"]
    r2 = rows[big]["parallel"] / rows[s]["parallel"]
    return (f"Memory: at N = {s} the per-env rows (about 1.7 KB per env) fit in a core's L2 cache, at N = {big} "
            f"they do not; one thread runs at {r1:.2f}x the N = {s} rate there, both cores at {r2:.2f}x (below 1: "
            f"the step waits for memory; at small N the Python shell's fixed cost per step weighs more).")


def _cpu_target() -> str:
    """The CPU numba compiles for and its widest SIMD (the same code runs at very different SIMD
    rates on hosts with and without AVX-512: compare runs only on the same target)."""
    import llvmlite.binding as llvm

    feats = llvm.get_host_cpu_features()
    simd = "AVX-512" if feats.get("avx512f") else "AVX2" if feats.get("avx2") else "SSE/other"
    return f"numba target {llvm.get_host_cpu_name()}, {simd}"


def _nsub(env_id: str) -> int:
    venv = gym.make_vec(env_id, num_envs=1, vectorization_mode="vector_entry_point")
    nsub = int(venv.unwrapped.config.physics_substeps)
    venv.close()
    return nsub


def _load() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> str:
    args = parse_args(argv)
    load = _load()
    rng = np.random.default_rng(args.seed)
    rows = {}
    for n in args.sizes:
        rows[n] = bench_size(args, n, rng)
        print(f"N={n}: " + ", ".join(f"{c} {fmt(v)}" for c, v in rows[n].items()), flush=True)
    n = max(args.sizes)
    steady, resets = steady_state(args, n) if args.burn else (None, None)
    if steady:
        print(f"steady state N={n}: " + ", ".join(f"{c} {fmt(v)}" for c, v in steady.items()), flush=True)
    prof = profile(args, n) if n >= dyn.BLOCK else None
    tier_prof = profile(args, n, args.tier_id) if n >= dyn.BLOCK else None
    machine = machine_throughput(args.budget, args.repeats)
    policy = bench_policy(args, n) if args.policy else float("nan")
    policy_libm = bench_policy(args, n, "libm") if args.policy else float("nan")
    cold = None
    if args.cold_start:
        cold = {"single": cold_start(args.env_id), "vector": cold_start(args.env_id, 64)}
        print(f"cold start: {cold}", flush=True)
    text = report(args, rows, load, _load(), prof, machine, policy, policy_libm, cold, tier_prof, steady, resets)
    return write_report(args.out, text)


if __name__ == "__main__":
    main()
