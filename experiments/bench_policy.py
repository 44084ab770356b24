"""Speed of a scripted controller (PROPOSED by default) in the batched evaluation loop against
the bare vector env it drives, in env-steps per second and ns per env-step.

    python -m experiments.bench_policy                          # N = 4096, 60 s episodes, best of 3
    python -m experiments.bench_policy --n 512 --episode-s 5 --repeats 1
    python -m experiments.bench_policy --controller PROPOSED_KF_DOB --env-id AUVFollow-Hard-v1 \
        --out results/bench_policy_kf_dob.md                   # an estimator-based baseline on a tier

Three measurements, interleaved ``--repeats`` times (the best of each is kept: other
processes only ever slow a run down):

(a) **env**: the native vector env (``parallel`` chosen automatically, as
    :func:`controllers.evaluation.evaluate_batched` does) reset with the seeds and stepped
    for one episode (T steps) with pre-computed zero actions; creation not timed;
(b) **predict**: the controller's ``predict`` alone, T calls on one fixed observation batch (the
    env's observations after a few controlled steps), ``episode_start`` all False;
(c) **evaluate_batched**: ``evaluate_batched([controller], seeds=range(N))`` end to end (env
    creation, reset, T steps of predict + step + reference + bookkeeping, the metrics).

One more run of (c), with the policy behind a thin timing proxy, splits (c) into predict,
reference and the rest (env step, loop bookkeeping, creation, reset, metrics). A warm-up of
each part runs first (numba compiles once and caches on disk). Writes the Markdown report to
``--out`` (default ``results/bench_policy.md``; ``results/tmp/`` with non-default settings).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numba
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from controllers import ALL_CONTROLLERS, MODEL_AWARE_CONTROLLERS, make_controller
from controllers.evaluation import evaluate_batched
from experiments.outputs import output_path, write_report

GOAL = 1.5e6  #: evaluate_batched with PROPOSED, env-steps/s at N = 4096


@dataclass
class Args:
    n: int = 4096  #: number of envs (one episode each)
    episode_s: float = 60.0  #: episode length [s]
    repeats: int = 3  #: interleaved repetitions (best kept)
    env_id: str = "AUVFollow-S4-v0"  #: the AUVFollow id benchmarked (v0 scenario or v1 tier)
    controller: str = "PROPOSED"  #: the scripted controller in the loop (controllers.ALL_CONTROLLERS)
    out: Path = Path("results/bench_policy.md")  #: Markdown output


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=Args.n, help="number of envs (default %(default)s)")
    p.add_argument("--episode-s", type=float, default=Args.episode_s, help="episode length [s] (default %(default)s)")
    p.add_argument("--repeats", type=int, default=Args.repeats, help="interleaved repeats (default %(default)s)")
    p.add_argument("--env-id", default=Args.env_id, help="AUVFollow id, v0 or v1 (default %(default)s)")
    p.add_argument("--controller", default=Args.controller,
                   help="scripted controller in the loop, or a learned-estimator run directory (default %(default)s)")
    p.add_argument("--out", type=Path, default=None,
                   help="Markdown output file (default: results/bench_policy.md; results/tmp/ with non-default "
                        "settings)")
    a = p.parse_args(argv)
    if a.controller not in ALL_CONTROLLERS + MODEL_AWARE_CONTROLLERS and not Path(a.controller).is_dir():
        p.error(f"--controller {a.controller!r} is invalid: must be one of "
                f"{list(ALL_CONTROLLERS + MODEL_AWARE_CONTROLLERS)} or a run directory")
    if a.n < 1 or a.repeats < 1 or not a.episode_s > 0:
        p.error("--n and --repeats must be >= 1, --episode-s > 0")
    a.out = output_path(a, p, Args.out)
    return Args(**vars(a))


def _env_kwargs(args: Args) -> dict[str, float]:
    return {"episode_s": args.episode_s, "steady_start_s": min(10.0, args.episode_s / 2)}


class _Timed:
    """A policy proxy that adds up the wall time of ``predict`` and ``reference``."""

    def __init__(self, policy: Any) -> None:
        self.policy, self.spec, self.name = policy, policy.spec, policy.name
        self.t_predict = self.t_reference = 0.0

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True):
        t0 = time.perf_counter()
        out = self.policy.predict(observation, state=state, episode_start=episode_start, deterministic=deterministic)
        self.t_predict += time.perf_counter() - t0
        return out

    def reference(self, observation: Any) -> np.ndarray:
        t0 = time.perf_counter()
        out = self.policy.reference(observation)
        self.t_reference += time.perf_counter() - t0
        return out


def time_env(venv: Any, n: int, steps: int) -> tuple[float, int]:
    """(seconds, episode ends) of a reset (seeds 0..n-1) and ``steps`` steps with zero actions."""
    zeros = np.zeros((n, 3), dtype=np.float32)
    seeds = list(range(n))
    ends = 0
    t0 = time.perf_counter()
    venv.reset(seed=seeds)
    for _ in range(steps):
        _, _, term, trunc, _ = venv.step(zeros)
        ends += int(np.count_nonzero(term | trunc))
    return time.perf_counter() - t0, ends


def _make(name: str, spec: Any) -> Any:
    """A fresh controller: by name, or the controller of a learned-estimator run directory."""
    if Path(name).is_dir():
        from agents.training.loading import load_agent

        return load_agent(name).controller()
    return make_controller(name, spec)


def time_predict(name: str, spec: Any, obs: np.ndarray, steps: int) -> float:
    """Seconds for ``steps`` calls of a fresh controller's predict on ``obs`` (after one untimed call)."""
    policy = _make(name, spec)
    start = np.zeros(obs.shape[0], dtype=bool)
    policy.predict(obs, episode_start=start)
    t0 = time.perf_counter()
    for _ in range(steps):
        policy.predict(obs, episode_start=start)
    return time.perf_counter() - t0


def time_evaluate(args: Args, spec: Any, proxy: bool = False, reuse: bool = True) -> tuple[float, int, _Timed | None]:
    """(seconds, env-steps, timing proxy or None) of one evaluate_batched run with the controller
    (``reuse=False``: its target estimator recomputes the commit after each peek)."""
    policy: Any = _make(args.controller, spec)
    if getattr(policy, "estimator", None) is not None:
        policy.estimator.reuse_peek = reuse
    timed = _Timed(policy) if proxy else None
    t0 = time.perf_counter()
    df = evaluate_batched([timed or policy], args.env_id, seeds=range(args.n), env_kwargs=_env_kwargs(args),
                          progress=False)
    return time.perf_counter() - t0, int(df["steps"].sum()), timed


def fixed_batch(venv: Any, name: str, spec: Any, n: int, steps: int = 20) -> np.ndarray:
    """The env's observations after ``steps`` steps of the controller (realistic values)."""
    obs, _ = venv.reset(seed=list(range(n)))
    policy = _make(name, spec)
    for _ in range(steps):
        obs = venv.step(policy.predict(obs)[0])[0]
    return obs


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def fmt(rate: float) -> str:
    return f"{rate / 1e6:.3f} M" if rate >= 1e6 else f"{rate / 1e3:.1f} k"


def run(args: Args) -> dict[str, Any]:
    """The measurements: best seconds of (a), (b), (c), the breakdown of one proxied (c)."""
    kw = _env_kwargs(args)
    venv = gym.make_vec(args.env_id, num_envs=args.n, vectorization_mode="vector_entry_point", **kw)
    spec = venv.unwrapped.task_spec
    T = spec.n_steps
    obs = fixed_batch(venv, args.controller, spec, args.n)  # also the env's warm-up (compilation of its kernels)
    time_predict(args.controller, spec, obs, 2)  # warm-up
    warm = _make(args.controller, spec)
    evaluate_batched([warm], args.env_id, seeds=range(min(args.n, 8)), env_kwargs=kw, progress=False)
    best = {"env": np.inf, "predict": np.inf, "evaluate": np.inf}
    has_estimator = getattr(warm, "estimator", None) is not None
    if has_estimator:
        best["evaluate_noreuse"] = np.inf
    env_steps = args.n * T
    for r in range(args.repeats):
        t, ends = time_env(venv, args.n, T)
        best["env"] = min(best["env"], t)
        best["predict"] = min(best["predict"], time_predict(args.controller, spec, obs, T))
        t, steps, _ = time_evaluate(args, spec)
        best["evaluate"] = min(best["evaluate"], t)
        if has_estimator:
            best["evaluate_noreuse"] = min(best["evaluate_noreuse"], time_evaluate(args, spec, reuse=False)[0])
        print(f"repeat {r + 1}: env {fmt(env_steps / best['env'])}, predict {fmt(env_steps / best['predict'])}, "
              f"evaluate_batched {fmt(steps / best['evaluate'])} env-steps/s (best so far)", flush=True)
    parallel = bool(venv.unwrapped.parallel)
    venv.close()
    t, steps_c, timed = time_evaluate(args, spec, proxy=True)
    return {"T": T, "env_steps": env_steps, "steps_c": steps, "best": best, "parallel": parallel, "ends": ends,
            "split": {"total": t, "predict": timed.t_predict, "reference": timed.t_reference, "steps": steps_c}}


def report(args: Args, res: dict[str, Any], load: str, load_after: str) -> str:
    T, n, best = res["T"], args.n, res["best"]
    rates = {"env": res["env_steps"] / best["env"], "predict": res["env_steps"] / best["predict"],
             "evaluate": res["steps_c"] / best["evaluate"]}
    threads = numba.get_num_threads()
    name = args.controller
    cmd = f"python -m experiments.bench_policy --n {n} --episode-s {args.episode_s:g} --repeats {args.repeats}"
    if name != Args.controller or args.env_id != Args.env_id:
        cmd += f" --controller {name} --env-id {args.env_id}"
    lines = [f"# {name} in the batched evaluation loop: {args.env_id}, N = {n}, {args.episode_s:g} s episodes "
             f"({T} steps)", "",
             f"`{cmd}`. "
             f"Machine: {_cpu()}, {os.cpu_count()} CPUs, Python "
             f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, gymnasium "
             f"{gym.__version__}; vector env parallel={res['parallel']} on {threads} numba threads; best of "
             f"{args.repeats} interleaved repeats; load average (1, 5, 15 min) before the run {load}, after it "
             f"{load_after} (other processes share the cores: every figure is a lower bound of what an idle "
             f"machine gives).", "",
             "| part | env-steps/s | ns per env-step |", "|---|---|---|"]
    parts = (("(a) vector env alone: reset + T steps, zero actions (creation not timed)", "env"),
             (f"(b) {name} `predict` alone: T calls on one fixed batch", "predict"),
             (f"(c) `evaluate_batched` with {name}, end to end (creation, reset, metrics included)", "evaluate"))
    if "evaluate_noreuse" in best:
        rates["evaluate_noreuse"] = res["steps_c"] / best["evaluate_noreuse"]
        parts += (("(c') the same with the target estimator's peek reuse off (`reuse_peek = False`: the commit "
                   "after `reference`'s peek recomputed; bit-identical scores)", "evaluate_noreuse"),)
    for label, key in parts:
        lines.append(f"| {label} | {fmt(rates[key])} | {1e9 / rates[key]:.0f} |")
    ns_ab = 1e9 / rates["env"] + 1e9 / rates["predict"]
    lines.append(f"| (a) + (b): env and predict back to back, nothing else | {fmt(1e9 / ns_ab)} | {ns_ab:.0f} |")
    lines += ["", f"(a) with zero actions the followers drift off: {res['ends']} episode ends in its {T} steps "
              f"(terminations, or truncation at the last step, then autoresets), whose resets and episode metrics "
              f"(done by the env) it includes, as (c) includes the env's metrics at the final step. (b) has no "
              f"`reference` call before it, so it computes the whole law; in (c) `predict` reuses the reference "
              f"computed for the same observation by the previous step's `reference`."]
    s = res["split"]
    per = 1e9 / s["steps"]
    rest = s["total"] - s["predict"] - s["reference"]
    lines += ["", f"Where (c) spends its time (one more run, the policy behind a timing proxy; "
              f"{fmt(s['steps'] / s['total'])} env-steps/s):", "",
              "| part of (c) | s | ns per env-step |", "|---|---|---|",
              f"| `predict` | {s['predict']:.3f} | {s['predict'] * per:.0f} |",
              f"| `reference` (own-reference metric) | {s['reference']:.3f} | {s['reference'] * per:.0f} |",
              f"| the rest: env step, loop bookkeeping, creation, reset, metrics | {rest:.3f} | {rest * per:.0f} |",
              f"| **total** | **{s['total']:.3f}** | **{s['total'] * per:.0f}** |", ""]
    r = rates["evaluate"]
    ratio = f"(c) / (a) = {r / rates['env']:.2f} (1.0 would mean the loop costs nothing beside the env)"
    if name == "PROPOSED" and args.env_id == Args.env_id:
        verdict = "met" if r >= GOAL else f"MISSED by {100 * (1 - r / GOAL):.0f} %"
        lines += [f"Goal: evaluate_batched with PROPOSED >= {fmt(GOAL)} env-steps/s: {fmt(r)}, {verdict}; {ratio}."]
    else:
        waits = rates["predict"] < rates["env"]
        lines += [f"{ratio}. The controller's `predict` costs {1e9 / rates['predict']:.0f} ns per env-step against "
                  f"the env's {1e9 / rates['env']:.0f} ns: " + ("**the batch waits for the controller**." if waits
                  else "the env, not the controller, is what the batch waits for.")]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    args = parse_args(argv)
    load = _load()
    res = run(args)
    return write_report(args.out, report(args, res, load, _load()))


if __name__ == "__main__":
    main()
