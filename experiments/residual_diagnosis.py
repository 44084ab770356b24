"""Why the PPO residual on PROPOSED_IMM_DOB learns nothing on Leader-Hard: what moves, what the
residual does, and whether its observation holds what it would need.

    python -m experiments.residual_diagnosis          # about 3 minutes; results/residual_diagnosis.md

The committed runs (results/benchmark/runs/bppo7-LeaderHard-residual-IMMDOB-s0..s2: residual on
PROPOSED_IMM_DOB, scale 0.1, the estimator block in the observation, 10 M steps) are read and
re-played; nothing here is trained or tuned, and nothing sees a test seed.

1. **Does the policy move?** From each run's ``progress.csv`` and ``eval.csv``: the policy's
   standard deviation, the update's KL divergence and clip fraction at the start and the end, and
   the evaluation curve (32 evaluation seeds from 990000).
2. **What the residual does**: closed loop on training seeds 100-163, the deterministic residual
   force ``scale * a * limits`` against the base's force, per axis, and the exploration noise
   ``scale * std`` (fractions of the force limits).
3. **The reward's signal**: per-episode returns of the same episodes; the share of their variance
   from the three largest deviations (lost or nearly lost targets dominate a batch's returns and
   the reward normaliser).
4. **What the observation lacks**: what a residual could correct is the base's error of the present
   reference point e = true - estimated (body frame; the base tracks its estimate). Can a
   memoryless function of the residual's observation predict e? A ridge regression and a 2 x 128
   MLP fitted on seeds 0-63 (closed loop under the committed residual, which is the base to 1e-3),
   scored on seeds 100-163: the mean norm of e before and after subtracting the prediction, and R^2.
   If the residual's observation cannot predict e, no policy on it can correct the estimate: the
   limit is the information, not the parametrisation or PPO.
5. **A scripted oracle residual** (sees the present target: not a follower, a diagnosis): the
   residual's own parametrisation, a = clip(a_base + clip(a_oracle - a_base, -s, s), -1, 1), where
   a_oracle is the same law (PROPOSED_IMM_DOB) on the perfect-link observation (the present, exact
   target; auv_follow_env.perfect_link), both laws' disturbance observers told the applied force.
   Nothing is learned: it is the best correction of that form a residual could make with the
   information, at the trained residual's authority s = 0.1 of the limits and above. On check
   seeds 100-163 of Leader-Medium and Leader-Hard: the steady-window IQM, the paired mean against
   the base with a 95 % bootstrap CI, and lost targets (a terminated episode scores 20 m). If the
   oracle residual at s = 0.1 closes much of the base's gap, the parametrisation has the room and
   what the trained residual lacks is the information.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env.metrics import true_reference_body
from experiments.outputs import output_path, write_report

RUNS = tuple(Path("results/benchmark/runs").glob("bppo7-LeaderHard-residual-IMMDOB-s*"))
ENV_ID = "AUVFollow-Leader-Hard-v1"
FIT_SEEDS = tuple(range(0, 64))
CHECK_SEEDS = tuple(range(100, 164))
STEADY_STEP = 200  #: t >= 10 s


def training_dynamics(run: Path) -> dict[str, float]:
    prog = pd.read_csv(run / "progress.csv")
    ev = pd.read_csv(run / "eval.csv")
    head, tail = prog.head(20), prog.tail(20)
    return {"std_first": float(prog["std_mean"].iloc[0]), "std_last": float(prog["std_mean"].iloc[-1]),
            "kl_first": float(head["approx_kl"].mean()), "kl_last": float(tail["approx_kl"].mean()),
            "clip_first": float(head["clip_frac"].mean()), "clip_last": float(tail["clip_frac"].mean()),
            "eval_first": float(ev["true_steady_mean_m"].iloc[0]),
            "eval_last": float(ev["true_steady_mean_m"].iloc[-1]),
            "eval_min": float(ev["true_steady_mean_m"].min()), "steps": int(prog["steps"].iloc[-1])}


def rollout(run: Path, seeds: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Closed loop under the committed residual, one episode per seed in one vector env: per
    steady, running step the residual's observation (unnormalised), the base and residual forces
    [fractions of the limits], the base's reference error e (true - estimated, body frame) and
    per episode the return."""
    import torch

    from agents.training import load_agent
    from agents.training.batched_obs import ESTIMATOR_INDEX

    agent = load_agent(run)
    venv = gym.make_vec(ENV_ID, num_envs=len(seeds), vectorization_mode="vector_entry_point")
    raw, info = venv.reset(seed=list(seeds))
    n = len(seeds)
    b = agent.builder
    b.reset()
    scale = float(agent.residual["scale"])
    w = b.obs_width
    at_est = w + 3  # after the env's fields and the base action
    alive = np.ones(n, dtype=bool)
    first = np.ones(n, dtype=bool)
    ret = np.zeros(n)
    out: dict[str, list] = {"feats": [], "base": [], "res": [], "err": [], "episode": []}
    for k in range(int(venv.unwrapped.task_spec.n_steps) if hasattr(venv, "unwrapped") else 1200):
        feats = b.observe(raw, first)
        with torch.no_grad():
            mean = agent.net.mean(agent.net.trunk(torch.as_tensor(agent.normalize(feats), dtype=torch.float32),
                                                  None, torch.as_tensor(first))[0]).numpy().astype(np.float64)
        if k >= STEADY_STEP:
            bx, by = true_reference_body(info)
            est = feats[:, at_est + ESTIMATOR_INDEX["est_ref_dx"]], feats[:, at_est + ESTIMATOR_INDEX["est_ref_dy"]]
            ok = alive & (feats[:, at_est + ESTIMATOR_INDEX["est_valid"]] > 0.5)
            out["feats"].append(feats[ok])
            out["base"].append(feats[ok, w:w + 3])
            out["res"].append(scale * mean[ok])
            out["err"].append(np.stack([bx - est[0], by - est[1]], axis=1)[ok])
            out["episode"].append(np.flatnonzero(ok))
        act = b.act(mean)
        raw, rew, term, trunc, info = venv.step(act)
        ret += np.where(alive, rew, 0.0)
        alive &= ~(term | trunc)
        first[:] = False
        if not alive.any():
            break
    venv.close()
    data = {key: np.concatenate(v) for key, v in out.items()}
    data["returns"] = ret
    data["std"] = float(np.exp(agent.net.log_std.detach().numpy()).mean())
    data["scale"] = scale
    return data


def fit_predictors(fit: dict, check: dict, epochs: int = 40, seed: int = 0) -> dict[str, float]:
    """Ridge and MLP from the (standardised) observation to e, scored on ``check``. The ridge
    penalty (1e-3 .. 1e3) and the MLP's epoch are chosen on the last quarter of the fitting
    episodes (validation), never on ``check``; the predictor 0 (no correction) is in both choices."""
    import torch

    X, Y, Xc, Yc = fit["feats"], fit["err"], check["feats"], check["err"]
    ep = fit["episode"]
    val = ep >= np.quantile(ep, 0.75)
    mu, sd = X[~val].mean(0), X[~val].std(0) + 1e-6
    Z, Zc = (X - mu) / sd, (Xc - mu) / sd

    def norm(y: np.ndarray, pred: np.ndarray) -> float:
        return float(np.linalg.norm(y - pred, axis=1).mean())

    A = np.hstack([Z, np.ones((len(Z), 1))])
    best = (norm(Y[val], 0.0 * Y[val]), None)
    for lam in 10.0 ** np.arange(-3, 4):
        At = A[~val]
        coef = np.linalg.solve(At.T @ At + lam * np.eye(A.shape[1]), At.T @ Y[~val])
        best = min(best, (norm(Y[val], A[val] @ coef), coef), key=lambda t: t[0])
    coef = best[1]
    Ac = np.hstack([Zc, np.ones((len(Zc), 1))])
    lin = np.zeros_like(Yc) if coef is None else Ac @ coef
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(Z.shape[1], 128), torch.nn.Tanh(), torch.nn.Linear(128, 128),
                              torch.nn.Tanh(), torch.nn.Linear(128, 2))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    zt, yt = torch.as_tensor(Z[~val], dtype=torch.float32), torch.as_tensor(Y[~val], dtype=torch.float32)
    zv, zc = torch.as_tensor(Z[val], dtype=torch.float32), torch.as_tensor(Zc, dtype=torch.float32)
    g = torch.Generator().manual_seed(seed)
    best_v, mlp = norm(Y[val], 0.0 * Y[val]), np.zeros_like(Yc)
    for _ in range(epochs):
        for idx in torch.randperm(len(zt), generator=g).split(1024):
            opt.zero_grad()
            loss = torch.linalg.vector_norm(net(zt[idx]) - yt[idx], dim=1).mean()  # the metric: a mean norm
            loss.backward()
            opt.step()
        with torch.no_grad():
            v = norm(Y[val], net(zv).numpy())
            if v < best_v:
                best_v, mlp = v, net(zc).numpy()

    def r2(pred: np.ndarray) -> float:
        return float(1.0 - ((Yc - pred) ** 2).sum() / ((Yc - Yc.mean(0)) ** 2).sum())

    return {"e_norm": norm(Yc, 0.0 * Yc), "e_median": float(np.median(np.linalg.norm(Yc, axis=1))),
            "ridge_norm": norm(Yc, lin), "ridge_r2": r2(lin), "ridge_none": coef is None,
            "mlp_norm": norm(Yc, mlp), "mlp_r2": r2(mlp),
            "mlp_median": float(np.median(np.linalg.norm(Yc - mlp, axis=1)))}


ORACLE_TIERS = ("Leader-Medium", "Leader-Hard")
ORACLE_SCALES = (0.1, 0.2, 0.5, 1.0)
BASE = "PROPOSED_IMM_DOB"


def oracle_residual(tier: str, seeds: tuple[int, ...], scale: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Per episode the steady-window mean true-reference error [m] and the terminated flag of
    the base (``scale`` None) or the scripted oracle residual at authority ``scale``, one vector env."""
    from agents.benchmark.protocol import _max_distance
    from auv_follow_env.metrics import tracking_metrics
    from auv_follow_env.perfect_link import perfect_link_observation
    from controllers import make_controller

    env_id = f"AUVFollow-{tier}-v1"
    n = len(seeds)
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    base, oracle = make_controller(BASE, spec), make_controller(BASE, spec)
    limits = np.asarray(spec.force_limits, dtype=np.float64)
    obs, info = venv.reset(seed=list(seeds))
    T = spec.n_steps
    err = np.full((n, T), np.nan)
    alive, term_any, length = np.ones(n, dtype=bool), np.zeros(n, dtype=bool), np.full(n, T)
    start = np.ones(n, dtype=bool)
    for k in range(T):
        a, _ = base.predict(obs, state=None, episode_start=start, deterministic=True)
        a = np.asarray(a, dtype=np.float64)
        if scale is not None:
            seen = perfect_link_observation(obs, info["true_target"], info["follower_pose"], spec.p_d)
            a_or, _ = oracle.predict(seen, state=None, episode_start=start, deterministic=True)
            a = np.clip(a + np.clip(np.asarray(a_or, dtype=np.float64) - a, -scale, scale), -1.0, 1.0)
            for law in (base, oracle):  # each law's observer hears the force applied, not its own command
                law.disturbance_observer.applied(a * limits)
        start[:] = False
        obs, _, term, trunc, info = venv.step(a.astype(np.float32))
        np.copyto(err[:, k], info["tracking_error"], where=alive)
        ended = alive & (term | trunc)
        length[ended] = k + 1
        term_any |= ended & term
        alive &= ~ended
        if not alive.any():
            break
    venv.close()
    times = spec.dt * np.arange(1, T + 1)
    steady = np.array([tracking_metrics(err[i, :length[i]], times[:length[i]], spec.steady_start_s)["steady_mean"]
                       for i in range(n)])
    return np.where(term_any, _max_distance(env_id), steady), term_any


def oracle_lines(seeds: tuple[int, ...] = CHECK_SEEDS) -> list[str]:
    from agents.benchmark.stats import iqm, stratified_bootstrap_ci

    lines = ["", "## 5. A scripted oracle residual (sees the present target; check seeds "
             f"{seeds[0]}-{seeds[-1]})", "",
             f"a = clip(a_base + clip(a_oracle - a_base, -s, s), -1, 1): the residual's form, with {BASE} on the "
             "perfect-link observation as a_oracle. Steady-window error [m]; a lost target scores 20 m.", "",
             "| tier | follower | IQM [m] | paired mean vs base, m (95 % CI) | paired median vs base [m] "
             "| lost targets |", "|---|---|---|---|---|---|"]
    for tier in ORACLE_TIERS:
        b, bt = oracle_residual(tier, seeds, None)
        lines.append(f"| {tier} | {BASE} (the base) | {float(iqm(b)):.3f} | - | - | {int(bt.sum())} |")
        for s in ORACLE_SCALES:
            x, xt = oracle_residual(tier, seeds, s)
            d = x - b
            _, lo, hi = stratified_bootstrap_ci([d], "mean")
            lines.append(f"| {tier} | oracle residual, s = {s:g} | {float(iqm(x)):.3f} | {d.mean():+.4f} "
                         f"[{lo:+.4f}, {hi:+.4f}] | {np.median(d):+.4f} | {int(xt.sum())} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="Markdown output (default: results/residual_diagnosis.md)")
    a = p.parse_args(argv)
    out = output_path(a, p, Path("results/residual_diagnosis.md"))
    t0 = time.perf_counter()
    runs = sorted(RUNS)
    if not runs:
        raise SystemExit("no committed residual runs under results/benchmark/runs "
                         "(bppo7-LeaderHard-residual-IMMDOB-s*)")
    lines = ["# Why the PPO residual on PROPOSED_IMM_DOB learns nothing on Leader-Hard", "",
             "Reproduce: `python -m experiments.residual_diagnosis` (method in its docstring). Committed runs "
             f"{', '.join(r.name for r in runs)}; training seeds only.", "",
             "## 1. Does the policy move?", "",
             "| run | steps | policy std (first -> last) | approx. KL (first 20 -> last 20 updates) | clip fraction "
             "| eval steady mean [m] (first -> min -> last) |", "|---|---|---|---|---|---|"]
    for r in runs:
        d = training_dynamics(r)
        lines.append(f"| {r.name} | {d['steps']:,} | {d['std_first']:.4f} -> {d['std_last']:.4f} | "
                     f"{d['kl_first']:.1e} -> {d['kl_last']:.1e} | {d['clip_first']:.3f} -> {d['clip_last']:.3f} | "
                     f"{d['eval_first']:.4f} -> {d['eval_min']:.4f} -> {d['eval_last']:.4f} |")
    lines += ["", "## 2. What the residual does (check seeds 100-163, steady window)", "",
              "Mean |force| as a fraction of each axis's limit (surge, sway, yaw).", "",
              "| run | base | residual (deterministic) | residual / base | exploration noise scale x std |",
              "|---|---|---|---|---|"]
    info_lines = ["", "## 4. What the observation lacks", "",
                  "The base's error of the present reference point e (true - estimated, body frame) on check seeds "
                  "100-163, and what is left after subtracting a memoryless predictor from the residual's "
                  "observation fitted on seeds 0-63. Mean norm [m] (the leaderboard's metric is a mean norm) and R^2.",
                  "The ridge penalty and the MLP's epoch are chosen on the last 16 fitting episodes (0: no "
                  "correction, if nothing beats it there).", "",
                  "| run's observation | mean norm of e (median) | after ridge | R^2 ridge | after MLP (median) "
                  "| R^2 MLP |", "|---|---|---|---|---|---|"]
    ret_lines = ["", "## 3. The reward's signal (check seeds 100-163)", "",
                 "| run | episodes | return mean | return std | variance share of the 3 largest deviations |",
                 "|---|---|---|---|---|"]
    for r in runs:
        chk = rollout(r, CHECK_SEEDS)
        base, res = np.abs(chk["base"]).mean(0), np.abs(chk["res"]).mean(0)
        lines.append(f"| {r.name} | {', '.join(f'{x:.3f}' for x in base)} | {', '.join(f'{x:.4f}' for x in res)} | "
                     f"{', '.join(f'{x:.3f}' for x in res / base)} | {chk['scale'] * chk['std']:.4f} |")
        dev = (chk["returns"] - chk["returns"].mean()) ** 2
        ret_lines.append(f"| {r.name} | {len(dev)} | {chk['returns'].mean():.1f} | {chk['returns'].std():.1f} | "
                         f"{np.sort(dev)[-3:].sum() / dev.sum():.2f} |")
        if r == runs[0]:
            fit = rollout(r, FIT_SEEDS)
            f = fit_predictors(fit, chk)
            info_lines.append(f"| {r.name} ({chk['feats'].shape[1]} fields, {len(fit['err']):,} fitting steps) | "
                              f"{f['e_norm']:.3f} ({f['e_median']:.3f}) | {f['ridge_norm']:.3f}"
                              f"{' (0 chosen)' if f['ridge_none'] else ''} | {f['ridge_r2']:.3f} | "
                              f"{f['mlp_norm']:.3f} ({f['mlp_median']:.3f}) | {f['mlp_r2']:.3f} |")
        print(f"{r.name}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    lines += ret_lines + info_lines + oracle_lines() + ["", f"Wall clock: {time.perf_counter() - t0:.0f} s.", ""]
    write_report(out, "\n".join(lines))


if __name__ == "__main__":
    main()
