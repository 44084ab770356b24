"""Speed of this checkout against another one (a git revision), side by side in one run.

    python -m experiments.bench_ab --baseline HEAD~3           # any revision of this repository
    python -m experiments.bench_ab --baseline HEAD~3 --sizes 0 1024 4096 --rounds 3   # 0: the single env
    python -m experiments.bench_ab --baseline main --sizes 0 4096 --cold 2   # and the cold start
    python -m experiments.bench_ab --baseline main --burn 1200   # the steady state of a long run

Absolute rates on a shared machine drift by tens of percent between runs (other virtual
machines, frequency), so a speed-up is only meaningful against a baseline measured in the
same minutes. This script exports the baseline revision into a temporary directory (``git
archive``; its numba cache is compiled there once), then runs the same measurement in
fresh subprocesses, alternating baseline and this checkout for ``--rounds`` rounds, and
keeps each side's best rate: the native vector env (one thread, and both cores), v0 and
the v1 tier, with pre-sampled random actions; size 0 is the single env through ``gym.make``
(steps/s, resets at episode ends included). Writes a Markdown table to ``--out``
(default results/tmp/bench_ab.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from experiments.bench_vector import cold_start
from experiments.outputs import write_report

ROOT = Path(__file__).resolve().parents[1]

#: what each subprocess runs (argv: env id, N, parallel 0/1, budget [s]); prints env-steps/s
_CHILD = r"""
import json, sys, time
import numpy as np, gymnasium as gym
import auv_follow_env
env_id, n, par = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "1"
budget, burn = float(sys.argv[4]), int(sys.argv[5])
acts = np.random.default_rng(0).uniform(-1, 1, (8, n, 3)).astype(np.float32)
if n == 0:  # the single env through gym.make, reset at episode ends
    env = gym.make(env_id)
    env.reset(seed=0)
    single = [a[0] for a in np.random.default_rng(0).uniform(-1, 1, (8, 1, 3)).astype(np.float32)]
    for j in range(burn):
        _, _, term, trunc, _ = env.step(single[j % 8])
        if term or trunc:
            env.reset()
    count, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < budget:
        for _ in range(100):
            _, _, term, trunc, _ = env.step(single[count % 8])
            count += 1
            if term or trunc:
                env.reset()
    print(json.dumps(count / (time.perf_counter() - t0)))
    raise SystemExit
venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", parallel=par)
venv.reset(seed=0)
for j in range(max(1, burn)):
    venv.step(acts[j % 8])
count, t0 = 0, time.perf_counter()
while time.perf_counter() - t0 < budget:
    venv.step(acts[count % 8])
    count += 1
print(json.dumps(count * n / (time.perf_counter() - t0)))
"""

CASES = (("AUVFollow-S4-v0", False), ("AUVFollow-S4-v0", True), ("AUVFollow-Hard-v1", False),
         ("AUVFollow-Hard-v1", True))


def _rate(src: Path, env_id: str, n: int, parallel: bool, budget: float, burn: int = 0) -> float:
    env = {**os.environ, "PYTHONPATH": str(src)}
    out = subprocess.run([sys.executable, "-c", _CHILD, env_id, str(n), "1" if parallel else "0", str(budget),
                          str(burn)],
                         cwd=src, env=env, capture_output=True, text=True, check=True)
    return float(json.loads(out.stdout.strip().splitlines()[-1]))


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", required=True, help="git revision to compare against (e.g. a commit or tag)")
    p.add_argument("--sizes", type=int, nargs="+", default=[4096], help="numbers of envs (default 4096)")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds per cell (default 3)")
    p.add_argument("--budget", type=float, default=2.0, help="timed seconds per measurement (default 2)")
    p.add_argument("--cold", type=int, default=0, metavar="ROUNDS",
                   help="also time the cold start (first reset + step of the single Hard-v1 env with an empty "
                        "numba cache) of each side, alternating, this many rounds (default 0: not timed)")
    p.add_argument("--burn", type=int, default=0, metavar="STEPS",
                   help="control steps before timing (default 0: right after the reset, when no episode has ended "
                        "yet; 1200, one episode, measures the steady state of a long run, autoresets included)")
    p.add_argument("--out", type=Path, default=ROOT / "results" / "tmp" / "bench_ab.md", help="Markdown output")
    a = p.parse_args(argv)
    if a.rounds < 1 or a.budget <= 0 or any(n < 0 for n in a.sizes) or a.cold < 0 or a.burn < 0:
        p.error("--rounds must be >= 1, --sizes >= 0 (0: the single env), --budget > 0, --cold >= 0, --burn >= 0")
    rev = subprocess.run(["git", "rev-parse", "--short", a.baseline], cwd=ROOT, capture_output=True, text=True)
    if rev.returncode != 0:
        p.error(f"--baseline {a.baseline!r} is not a revision of this repository")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="auv-ab-") as tmp:
        base = Path(tmp)
        archive = subprocess.run(["git", "archive", a.baseline], cwd=ROOT, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
        rows = []
        for n in a.sizes:
            for env_id, par in (c for c in CASES if n > 0 or not c[1]):
                best = {"baseline": 0.0, "this": 0.0}
                for _ in range(a.rounds):
                    for side, src in (("baseline", base), ("this", ROOT)):
                        best[side] = max(best[side], _rate(src, env_id, n, par, a.budget, a.burn))
                rows.append((n, env_id, par, best["baseline"], best["this"]))
                print(f"N={n} {env_id} parallel={par}: {best['baseline'] / 1e6:.3f} M -> {best['this'] / 1e6:.3f} M",
                      flush=True)
        cold = {"baseline": [], "this": []}
        for _ in range(a.cold):
            for side, src in (("baseline", base), ("this", ROOT)):
                c = cold_start("AUVFollow-Hard-v1", 0, root=src)
                cold[side].append(c)
                print(f"cold start {side}: {c['cold']:.1f} s wall, {c['cold_cpu']:.1f} s CPU; "
                      f"cached {c['cached']:.2f} s", flush=True)
    lines = [f"# This checkout ({head}) against {a.baseline} ({rev.stdout.strip()}), env-steps/s", "",
             f"Native vector env, random actions, {a.budget:g} s per measurement in a fresh process (numba cache "
             f"warm; timed after {a.burn} control steps), baseline and this checkout alternating for {a.rounds} "
             f"rounds, best kept; load average before the run {load}, after it "
             f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}. Default settings "
             f"(each revision's default sin/cos: glibc's up to 0.1.0, the SIMD polynomial since 0.2.0).", "",
             "| N | env | threads | baseline | this checkout | speed-up |", "|---|---|---|---|---|---|"]
    for n, env_id, par, b, t in rows:
        size = "single env (gym.make)" if n == 0 else n
        lines.append(f"| {size} | {env_id} | {'both cores' if par else 'one'} | {b / 1e6:.3f} M | {t / 1e6:.3f} M | "
                     f"{t / b:.2f}x |")
    if a.cold:
        lines += ["", f"Cold start: first `reset(); step(a)` of `gym.make('AUVFollow-Hard-v1')` in a new process "
                  f"with an empty numba cache (import excluded), then the same with that cache; {a.cold} "
                  "alternating rounds, the smallest kept (CPU seconds are less sensitive to other processes "
                  "than wall seconds).", "",
                  "| | baseline | this checkout | ratio |", "|---|---|---|---|"]
        for key, label, unit in (("cold", "cold start, wall", "s"), ("cold_cpu", "cold start, CPU", "s"),
                                 ("cached", "cached start, wall", "s")):
            b = min(c[key] for c in cold["baseline"])
            t = min(c[key] for c in cold["this"])
            lines.append(f"| {label} | {b:.2f} {unit} | {t:.2f} {unit} | {t / b:.2f}x |")
    return write_report(a.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
