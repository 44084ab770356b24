"""The benchmark protocol: one function scores any set of policies on the tiers' published
test seeds and writes the leaderboard.

>>> from agents.benchmark import benchmark
>>> result = benchmark(["PID", "PROPOSED", "results/benchmark/runs/ppo-residual"], tiers=["S4", "Hard"],
...                    out_dir="results/benchmark")          # doctest: +SKIP
>>> result.leaderboard                                        # doctest: +SKIP

Protocol (written once, here; the CLI ``auv-follow benchmark``, the sweep, the README's tables
and the HTML report all call :func:`benchmark` / :func:`leaderboard`):

* **Tiers and seeds.** A tier is a v1 tier (``Easy``, ``Medium``, ``Hard``, ``Extreme`` ->
  ``AUVFollow-<tier>-v1``, scored on the test seeds the environment package publishes) or a
  paper scenario (``S1`` ... ``S4`` -> ``AUVFollow-S<k>-v0``, scored on :data:`V0_TEST_SEEDS`,
  our choice: 100 seeds disjoint from every seed the training code uses).
* **Policies.** A scripted controller by name (``"PROPOSED"``), a trained agent by run
  directory, or a group of runs of one method (``"label=run_a,run_b,run_c"`` or a directory
  whose sub-directories are runs): the runs of a group are its training seeds.
* **Scores.** Per episode, the true-reference tracking metrics of eq. (65) (steady state
  t >= 10 s and full run). An episode that ends by termination (target lost) scores
  ``max_distance_m`` (the loss threshold) on every error metric - it is at least that bad.
* **Aggregates** per (tier, policy): IQM (interquartile mean, 25 % trimmed on each side,
  as rliable) and mean, each with a 95 % percentile **stratified bootstrap** CI (strata =
  the group's training runs; one stratum for a scripted controller; the runs share the test
  seeds, so one draw of seed indices resamples every run alike), ``scipy.stats.bootstrap``
  with a fixed seed so a rerun gives the same numbers;
  termination rate; and the **probability of improvement** over the tier's best classical
  baseline (the scripted controller with the lowest steady-state IQM), rliable's definition
  for lower-is-better scores: P(X < Y) + P(X = Y) / 2 over all pairs of episodes, with a
  bootstrap CI.

The package, by concern (data flows one way: ``run`` -> ``evaluation`` -> ``policies`` ->
``protocol`` / ``stats``; ``floors``, ``report``, ``compare`` and ``sweep`` sit on top):
``stats`` (pure array statistics), ``protocol`` (tiers, seeds, metrics), ``policies`` (policy
specs and building them), ``evaluation`` (batched evaluation and the cache), ``leaderboard``
(tables, summary, PNG), ``outputs`` (files written as one set, :func:`load_result`),
``traces`` (per-step episodes for the report), ``run`` (:func:`benchmark`), ``floors``,
``report``, ``compare``, ``sweep``.
"""

from __future__ import annotations

from agents.benchmark.evaluation import evaluate_tier
from agents.benchmark.leaderboard import (
    benchmark_summary,
    goal_check,
    leaderboard,
    leaderboard_markdown,
    paired_difference,
    plot_leaderboard,
    scores,
)
from agents.benchmark.outputs import BenchmarkResult, OutputWriteError, load_result, provenance, replace_set
from agents.benchmark.policies import IncompatiblePolicy, PolicySpec, parse_policy
from agents.benchmark.protocol import (
    ERROR_METRICS,
    LEADER_TIERS,
    LEADERBOARD_METRICS,
    RESERVED_LABELS,
    V0_TEST_SEEDS,
    V0_TIERS,
    V1_TIERS,
    available_tiers,
    check_labels,
    check_seed_list,
    default_test_seeds,
    resolve_tier,
    tier_test_seeds,
)
from agents.benchmark.run import benchmark
from agents.benchmark.stats import (
    DEFAULT_RESAMPLES,
    MAX_RESAMPLES,
    iqm,
    probability_of_improvement,
    stratified_bootstrap_ci,
)

__all__ = ["BenchmarkResult", "DEFAULT_RESAMPLES", "ERROR_METRICS", "IncompatiblePolicy", "LEADERBOARD_METRICS",
           "MAX_RESAMPLES", "OutputWriteError", "PolicySpec", "RESERVED_LABELS", "V0_TEST_SEEDS",
           "V0_TIERS", "V1_TIERS", "LEADER_TIERS", "available_tiers", "benchmark", "benchmark_summary", "check_labels",
           "check_seed_list", "default_test_seeds", "evaluate_tier", "goal_check", "iqm", "leaderboard",
           "leaderboard_markdown", "load_result", "paired_difference", "parse_policy", "plot_leaderboard",
           "probability_of_improvement", "provenance", "replace_set", "resolve_tier", "scores",
           "stratified_bootstrap_ci", "tier_test_seeds"]
