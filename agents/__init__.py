"""Learned agents and the benchmark: ``agents.training`` makes and loads run directories (SB3
and the batched PPO, residual or from scratch), ``agents.benchmark`` scores any policy on the
tiers' published test seeds (leaderboard, floors, report, sweeps), ``agents.cli`` is the
``auv-follow`` command. Data flows one way: cli -> benchmark -> training. See ``agents/README.md``."""
