"""Reproduce Section 4 of Zhang et al. (2026): Tables 4-7, Figures 3-4 and a claims audit.

    python -m experiments.reproduce_paper             # one run per scenario + 100-seed CIs
    python -m experiments.reproduce_paper --seeds 0   # only the paper's design: one run per scenario

Writes to ``results/paper/`` (see ``--out``): ``tables.csv``, ``tables.md``,
``fig3_scenarios.png``, ``fig4_s4_zoom.png``, ``claims.md``, ``summary.json``.
One plant, one target trajectory per scenario (seed ``--seed``), one gain set, shared by
all four controllers; nothing is tuned toward a published number.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import pandas as pd

from auv_follow_env.metrics import METRIC_KEYS
from controllers.evaluation import evaluate_controllers
from experiments import paper

REFS = {"own": "own reference (paper's convention)", "true": "true reference (present target)"}


@dataclass
class Args:
    out: Path = Path("results/paper")  #: output directory
    seed: int = 0  #: seed of the single run per scenario (target phases, current, disturbances)
    seeds: int = 100  #: if > 0, also run this many seeds (0..seeds-1) and report mean +- 95% CI
    figures: bool = True  #: draw Figures 3 and 4
    diagnostic: bool = False  #: also run the DIAGNOSTIC present-velocity feedforward (not the paper's law)
    progress: bool = True  #: progress bars


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Args.out, help="output directory (default results/paper)")
    p.add_argument("--seed", type=int, default=Args.seed, help="seed of the single run per scenario")
    p.add_argument("--seeds", type=int, default=Args.seeds,
                   help="many-seed mode: also run seeds 0..N-1 and report mean +- 95%% CI (default 100; 0 = off)")
    p.add_argument("--no-figures", dest="figures", action="store_false", help="skip the PNG figures")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.add_argument("--diagnostic", action="store_true",
                   help="also run the DIAGNOSTIC variant of NOTES.md item 3 (feedforward (26) and r_d (29) fed "
                        "by the present, undelayed target velocity - information a real follower lacks); "
                        "reported separately in claims.md, never part of the tables")
    a = p.parse_args(argv)
    if a.seed < 0:
        p.error(f"--seed must be >= 0, got {a.seed}")
    if a.seeds < 0 or a.seeds == 1:
        p.error(f"--seeds must be 0 (off) or >= 2, got {a.seeds}")
    return Args(**vars(a))


def long_results(metrics: pd.DataFrame) -> pd.DataFrame:
    """Our metrics in the paper's long form: scenario, window, metric, controller, ref, value."""
    rows = []
    for _, r in metrics.iterrows():
        for ref in REFS:
            for key in METRIC_KEYS:
                window, metric = key.split("_")
                rows.append({"scenario": r.scenario, "window": window, "metric": metric,
                             "controller": r.policy, "ref": ref, "seed": r.seed, "value": r[f"{ref}_{key}"]})
    return pd.DataFrame(rows)


def comparison_table(ours: pd.DataFrame, pub: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, window, metric, controller): paper, ours_own, ours_true."""
    piv = ours.pivot_table(index=["scenario", "window", "metric", "controller"], columns="ref",
                           values="value").rename(columns={"own": "ours_own", "true": "ours_true"})
    pubi = pub.set_index(["scenario", "window", "metric", "controller"]).value.rename("paper")
    t = piv.join(pubi).reset_index()[["scenario", "window", "metric", "controller", "paper", "ours_own",
                                      "ours_true"]]
    order = {c: i for i, c in enumerate(paper.CONTROLLERS)}
    morder = {m: i for i, m in enumerate(paper.METRICS)}
    t = t.sort_values(by=["scenario", "window", "metric", "controller"],
                      key=lambda s: s.map(order) if s.name == "controller" else
                      (s.map(morder) if s.name == "metric" else s))
    return t.reset_index(drop=True)


_LABEL = {"mean": "Mean error (m)", "rmse": "RMSE (m)", "max": "Maximum error (m)"}


def markdown_tables(table: pd.DataFrame, ci: pd.DataFrame | None = None) -> str:
    out = ["# Tables 4-7 reproduced", "",
           "Each cell: **paper** / ours against the controller's **own** reference (the paper's "
           "convention) / ours against the **true** reference (present, undelayed target; what the env "
           "rewards). Metres. Full run 0-60 s; steady state t >= 10 s.", ""]
    for k, sc in enumerate(paper.SCENARIOS):
        out += [f"## Table {k + 4}: Scenario {sc}", "",
                "| Metric | " + " | ".join(paper.CONTROLLERS) + " |",
                "|---|" + "---|" * len(paper.CONTROLLERS)]
        for win, title in (("full", "Full run"), ("steady", "Steady state (first 10 s excluded)")):
            out.append(f"| *{title}* |" + " |" * len(paper.CONTROLLERS))
            for m in paper.METRICS:
                cells = []
                for c in paper.CONTROLLERS:
                    r = table[(table.scenario == sc) & (table.window == win) & (table.metric == m)
                              & (table.controller == c)].iloc[0]
                    cells.append(f"{r.paper:.3f} / {r.ours_own:.3f} / {r.ours_true:.3f}")
                out.append(f"| {_LABEL[m]} | " + " | ".join(cells) + " |")
        out.append("")
    if ci is not None:
        n = int(ci.n.iloc[0])
        out += [f"# Over {n} seeds: mean +- 95% confidence half-width", "",
                "Seeds vary the target's manoeuvre phases, the current and the disturbances; the "
                "plant, gains and scenario settings are fixed.", ""]
        for ref in REFS:
            for sc in paper.SCENARIOS:
                out += [f"### {sc}, {REFS[ref]}", "", "| Metric | " + " | ".join(paper.CONTROLLERS) + " |",
                        "|---|" + "---|" * len(paper.CONTROLLERS)]
                for win in paper.WINDOWS:
                    for m in paper.METRICS:
                        cells = []
                        for c in paper.CONTROLLERS:
                            r = ci[(ci.scenario == sc) & (ci.window == win) & (ci.metric == m)
                                   & (ci.controller == c) & (ci.ref == ref)].iloc[0]
                            cells.append(f"{r['mean']:.3f} +- {r.ci95:.3f}")
                        out.append(f"| {win} {m} | " + " | ".join(cells) + " |")
                out.append("")
    return "\n".join(out)


def seed_statistics(ours: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for key, g in ours.groupby(["scenario", "window", "metric", "controller", "ref"]):
        mean, half = paper.mean_ci(g.value.to_numpy())
        rows.append(dict(zip(["scenario", "window", "metric", "controller", "ref"], key, strict=True),
                         mean=mean, ci95=half, n=len(g)))
    return pd.DataFrame(rows)


def audit(table: pd.DataFrame) -> tuple[str, list[dict]]:
    """Check every claim against the paper's own numbers and ours (both references)."""
    results = []
    lines = ["# Claims audit", "",
             "Each quantitative claim of Section 4.3 and the conclusions, checked on the paper's own "
             "Tables 4-7 and on ours, against the controller's own reference (the paper's metric) and "
             "against the true reference (the task).", "",
             "| Claim | Where | Statement | Paper's tables | Ours, own ref | Ours, true ref |",
             "|---|---|---|---|---|---|"]
    details = []
    frames = {"paper": table.rename(columns={"paper": "value"}),
              "own": table.rename(columns={"ours_own": "value"}),
              "true": table.rename(columns={"ours_true": "value"})}
    for cl in paper.CLAIMS:
        verdicts = {}
        for src, df in frames.items():
            ok, why = cl.check(df[["scenario", "window", "metric", "controller", "value"]])
            verdicts[src] = ok
            details.append(f"- **{cl.id} / {src}**: {'holds' if ok else 'does not hold'}: {why}")
            results.append({"claim": cl.id, "source": src, "holds": bool(ok), "numbers": why})
        yn = {k: ("holds" if v else "**does not hold**") for k, v in verdicts.items()}
        lines.append(f"| {cl.id} | {cl.where} | {cl.text} | {yn['paper']} | {yn['own']} | {yn['true']} |")
    lines += ["", "## Numbers", ""] + details
    bad = paper.paper_consistency()
    lines += ["", "## Internal consistency of the published tables", "",
              "For any set of samples RMSE^2 <= max * mean. Rows of Tables 4-7 that break it "
              "(they cannot come from one uniformly sampled run):", ""]
    lines += ([f"- {r.scenario} {r.window} {r.controller}: RMSE^2 = {r['rmse^2']:.5f} > max*mean = "
               f"{r['max*mean']:.5f}" for _, r in bad.iterrows()] or ["- none"])
    return "\n".join(lines) + "\n", results


def mismatch_floor_section(table: pd.DataFrame) -> str:
    """Why PROPOSED cannot beat ROBUST_ONLY on the own reference here: a steady error floor.

    In steady surge at speed u the unmodelled drag (X_u - X_hat_u) u_r is balanced by the inner
    loop's K_u e_u + rho_u sat(e_u / phi_u), i.e. (inside the boundary layer) e_u = dX u_r /
    (K_u + rho_u / phi_u); the outer loop turns that velocity deficit into a position error
    e_p = e_u / K_p. The floor is the same with or without prediction.
    """
    import auv_follow_env
    from controllers.hierarchical import Gains

    g = Gains()
    lines = ["", "## Analysis: the steady own-reference error is a model-mismatch floor", "",
             "In steady following at the target's mean speed v_t, the unmodelled drag dX_u v_t is balanced by "
             "K_u e_u + rho_u e_u / phi_u, and the outer loop turns the velocity deficit into a position error "
             "e_p = dX_u v_t / ((K_u + rho_u / phi_u) K_p), shared by ROBUST_ONLY and PROPOSED (current ignored):",
             "", "| Scenario | dX_u (N s/m) | predicted floor (m) | ROBUST_ONLY own steady mean | "
             "PROPOSED own steady mean |", "|---|---|---|---|---|"]
    for sc in paper.SCENARIOS:
        cfg = auv_follow_env.make_config(sc)
        dx = cfg.true_vehicle.X_u - cfg.nominal.X_u
        floor = dx * cfg.scenario.target.speed / ((g.K_u + g.rho[0] / g.phi[0]) * g.K_p)
        sel = table[(table.scenario == sc) & (table.window == "steady") & (table.metric == "mean")]
        ro = float(sel[sel.controller == "ROBUST_ONLY"].ours_own.iloc[0])
        pr = float(sel[sel.controller == "PROPOSED"].ours_own.iloc[0])
        lines.append(f"| {sc} | {dx:.2f} | {floor:.4f} | {ro:.4f} | {pr:.4f} |")
    lines += ["", "Where the floor dominates (S1-S3), no change to the reference generation can make one "
              "robust variant beat the other on this metric; in S4 the manoeuvres add the predictor's "
              "O(tau a_t) feedforward mismatch on top (NOTES.md, item 2)."]
    return "\n".join(lines) + "\n"


def diagnostic_section(table: pd.DataFrame, seed: int) -> str:
    """Run the DIAGNOSTIC variant and compare it with ROBUST_ONLY on the own-reference metric."""
    import auv_follow_env
    from controllers.diagnostic import AppendPresentTargetVelocity, PresentFeedforwardController
    from controllers.evaluation import evaluate

    lines = ["", "## DIAGNOSTIC (not the paper's equations): present-velocity feedforward", "",
             "NOTES.md item 3: PROPOSED with the feedforward (26) and r_d (29) fed by the *present* target "
             "velocity, which a real follower does not have. Steady-state RMSE against the own reference, "
             "and its reduction against ROBUST_ONLY (paper: 33 / 54 / 46 / 50 %):", "",
             "| Scenario | ROBUST_ONLY | PROPOSED | DIAGNOSTIC | DIAGNOSTIC vs ROBUST_ONLY | error to true ref |",
             "|---|---|---|---|---|---|"]
    for sc in paper.SCENARIOS:
        spec = auv_follow_env.make_task_spec(sc)
        m = evaluate(PresentFeedforwardController(spec), f"AUVFollow-{sc}-v0", [seed],
                     env_wrapper=AppendPresentTargetVelocity, progress=False).iloc[0]
        sel = table[(table.scenario == sc) & (table.window == "steady") & (table.metric == "rmse")]
        ro = float(sel[sel.controller == "ROBUST_ONLY"].ours_own.iloc[0])
        pr = float(sel[sel.controller == "PROPOSED"].ours_own.iloc[0])
        lines.append(f"| {sc} | {ro:.4f} | {pr:.4f} | {m.own_steady_rmse:.4f} | "
                     f"{100 * (1 - m.own_steady_rmse / ro):+.1f}% | {m.true_steady_rmse:.4f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    metrics, traj = evaluate_controllers(seeds=[args.seed], trajectories=True, progress=args.progress)
    t_runs = time.perf_counter() - t0
    pub = paper.paper_results()
    table = comparison_table(long_results(metrics), pub)
    table.to_csv(args.out / "tables.csv", index=False)
    ci, t_seeds = None, 0.0
    if args.seeds:
        t1 = time.perf_counter()
        many = evaluate_controllers(seeds=range(args.seeds), progress=args.progress)
        t_seeds = time.perf_counter() - t1
        ci = seed_statistics(long_results(many))
        ci.to_csv(args.out / "tables_seeds.csv", index=False)
    (args.out / "tables.md").write_text(markdown_tables(table, ci))
    text, results = audit(table)
    text += mismatch_floor_section(table)
    if args.diagnostic:
        text += diagnostic_section(table, args.seed)
    (args.out / "claims.md").write_text(text)
    if args.figures:
        from experiments.figures import figure3, figure4

        figure3(traj, args.out / "fig3_scenarios.png")
        figure4(traj, args.out / "fig4_s4_zoom.png")
    summary = {"args": {k: str(v) for k, v in asdict(args).items()}, "runs": len(metrics),
               "seconds_for_16_runs": round(t_runs, 3), "seconds_for_seed_runs": round(t_seeds, 3),
               "claims": results}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{len(metrics)} runs in {t_runs:.2f} s" + (f"; {16 * args.seeds} seed runs in {t_seeds:.2f} s"
                                                       if args.seeds else "") + f"; wrote {args.out}/")
    for r in results:
        if r["source"] != "paper":
            continue
        own = next(x for x in results if x["claim"] == r["claim"] and x["source"] == "own")["holds"]
        true = next(x for x in results if x["claim"] == r["claim"] and x["source"] == "true")["holds"]
        print(f"  {r['claim']}: paper's tables {'holds' if r['holds'] else 'FAILS'}; own ref "
              f"{'holds' if own else 'FAILS'}; true ref {'holds' if true else 'FAILS'}")
    return summary


if __name__ == "__main__":
    main()
