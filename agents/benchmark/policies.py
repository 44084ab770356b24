"""Policy specs: a scripted controller by name, a trained run (or a group of runs), or a
user's ``module:Class``; parsing them and building the batched policy for an env."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.protocol import resolve_tier
from auv_follow_env._files import check_size


@dataclass(frozen=True)
class PolicySpec:
    """One leaderboard entry: a scripted controller, or a learned method with its runs."""

    label: str  #: name on the leaderboard
    kind: str  #: "classical" (scripted controller), "learned" or "external" (a user's ``module:Class``)
    controller: str | None = None  #: controller name (classical) or ``module:Class`` (external)
    runs: tuple[str, ...] = ()  #: run directories (learned; one per training seed)
    tiers: tuple[str, ...] = ()  #: the tiers it is scored on (empty: every benchmarked tier)


def _controllers() -> tuple[str, ...]:
    """Every registered scripted controller (the paper's four and, where present, ours)."""
    import controllers

    return (tuple(getattr(controllers, "ALL_CONTROLLERS", controllers.CONTROLLERS))
            + tuple(getattr(controllers, "MODEL_AWARE_CONTROLLERS", ())))


def _is_run(p: Path) -> bool:
    return (p / "model.zip").is_file() and (p / "config.yaml").is_file()


def parse_policy(item: str | Path | PolicySpec) -> PolicySpec:
    """A :class:`PolicySpec` from a controller name, a run directory, a directory of runs
    (one method, its runs = training seeds), ``"label=run_a,run_b"`` or a user's controller
    class ``"[label=]module.path:ClassName"`` (:func:`_import_external`); a suffix
    ``@Tier[+Tier]`` scores it on those tiers only (e.g. an expensive ``MPC@Hard``).

    Raises:
        ValueError: the item is none of these (names the valid controllers).
    """
    if isinstance(item, PolicySpec):
        return item
    text = str(item)
    if "@" in text and not Path(text).exists():
        base, _, only = text.rpartition("@")
        tiers = tuple(resolve_tier(t)[0] for t in only.split("+") if t)
        if not tiers:
            raise ValueError(f"policy={text!r} is invalid: give tiers after '@', e.g. MPC@Hard or MPC@Hard+Extreme")
        return dataclasses.replace(parse_policy(base), tiers=tiers)
    if text in _controllers():
        return PolicySpec(label=text, kind="classical", controller=text)
    ext = _EXTERNAL.match(text)
    if ext is not None and not Path(text).exists():
        target = ext.group("target")
        _import_external(target)  # refuses an unknown module or class now, naming it
        return PolicySpec(label=ext.group("label") or target.rsplit(":", 1)[1], kind="external", controller=target)
    label = None
    paths = [text]
    if "=" in text and not Path(text).exists():
        label, rest = text.split("=", 1)
        paths = [p for p in rest.split(",") if p]
    runs: list[str] = []
    for ptext in paths:
        p = Path(ptext)
        if _is_run(p):
            runs.append(str(p))
        elif p.is_dir() and any(_is_run(c) for c in p.iterdir()):
            runs.extend(str(c) for c in sorted(p.iterdir()) if _is_run(c))
            label = label or p.name
        else:
            raise ValueError(f"policy={ptext!r} is invalid: must be a controller name {list(_controllers())}, a run "
                             f"directory (with model.zip and config.yaml), a directory of runs, or label=run,run")
    if not runs:
        raise ValueError(f"policy={text!r} names no runs")
    for r in runs:
        _check_complete_run(Path(r), text)
    if label is None:
        from agents.training.loading import load_agent

        label = load_agent(runs[0]).name if len(runs) == 1 else Path(runs[0]).parent.name
    return PolicySpec(label=label, kind="learned", runs=tuple(runs))


#: ``[label=]module.path:ClassName`` - a user's controller class (see :func:`_import_external`)
_EXTERNAL = re.compile(r"^(?:(?P<label>[^=]+)=)?(?P<target>[A-Za-z_][\w.]*:[A-Za-z_]\w*)$")


def _import_external(target: str) -> type:
    """The class ``module.path:ClassName`` (the current directory is searched too, so a file
    next to you works with the console script). Its protocol: ``Class(task_spec)`` builds the
    policy for one tier; ``predict(observation, state=None, episode_start=None,
    deterministic=True) -> (action, state)`` takes a batch ``(n_envs, obs_dim)`` and returns
    actions in [-1, 1] of shape ``(n_envs, 3)`` (where the benchmark has one observation - the
    unbatched evaluation, the replay episode - it passes a batch of one: :class:`_BatchProtocol`);
    an optional ``reset()`` is called at the start of the episodes. Importing runs the module:
    name only code you trust (building a report never imports it).

    Raises:
        ValueError: the module cannot be imported (or raises while it is), or has no such class
            with a ``predict``.
    """
    import importlib
    import os
    import sys

    module, _, cls_name = target.partition(":")
    cwd = os.getcwd()
    added = cwd not in sys.path
    if added:
        sys.path.append(cwd)
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise ValueError(f"policy={target!r} is invalid: module {module!r} cannot be imported ({exc}); give "
                         "module.path:ClassName of an installed module or one under the current directory") from None
    except Exception as exc:  # noqa: BLE001 (importing runs the user's module: it can raise anything)
        text = " ".join(str(exc).split())[:300]
        raise ValueError(f"policy={target!r}: importing module {module!r} raised {type(exc).__name__}"
                         + (f": {text}" if text else "")) from exc
    finally:
        if added:
            sys.path.remove(cwd)
    cls = getattr(mod, cls_name, None)
    if not isinstance(cls, type) or not callable(getattr(cls, "predict", None)):
        raise ValueError(f"policy={target!r} is invalid: {module} has no class {cls_name!r} with a predict method "
                         "(see docs/benchmark.md, 'Your own controller')")
    return cls


def _check_complete_run(run: Path, policy: str) -> None:
    """Refuse a run whose training did not finish: ``config.yaml`` records ``result.interrupted:
    true`` (Ctrl-C or a signal) or has no ``result`` (still training, or killed)."""
    import yaml

    cfg_path = run / "config.yaml"
    try:
        cfg = yaml.safe_load(check_size(cfg_path, "text").read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ValueError(f"policy={policy!r}: {cfg_path} is not readable YAML ({type(exc).__name__})") from None
    result = cfg.get("result") if isinstance(cfg, dict) else None
    if not isinstance(result, dict):
        raise ValueError(f"policy={policy!r}: run {run} has no 'result' in {cfg_path} (training still running or "
                         "killed): only finished runs can be benchmarked")
    if result.get("interrupted"):
        steps = result.get("num_timesteps")
        total = (cfg.get("run") or {}).get("total_timesteps") if isinstance(cfg.get("run"), dict) else None
        raise ValueError(f"policy={policy!r}: run {run} is an interrupted training run (result.interrupted: true in "
                         f"{cfg_path}, {steps} of {total} steps): finish it with `auv-follow train --resume` or "
                         "leave it out")


class _ObsPrefix:
    """Feed a policy the first ``width`` observation fields (a v0-trained agent on a v1 env:
    the v1 layout starts with the 16 v0 fields)."""

    def __init__(self, policy: Any, width: int) -> None:
        self.policy, self.width = policy, int(width)
        self.name = getattr(policy, "name", type(policy).__name__)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation)[..., : self.width]
        return self.policy.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)


class _BatchProtocol:
    """A user's controller as docs/benchmark.md describes it: ``predict`` always gets a batch
    ``(n_envs, obs_dim)`` and returns ``(n_envs, 3)``. A single observation (the unbatched
    evaluation, the replay episode of ``traces.parquet``) is passed as a batch of one and the
    action of that one env returned; the optional ``reset()`` is called at the start of each
    episode (``episode_start`` all true)."""

    def __init__(self, policy: Any, label: str) -> None:
        self.policy, self.name = policy, label
        if callable(getattr(policy, "reference", None)):
            self.reference = policy.reference

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[Any, Any]:
        obs = np.asarray(observation)
        single = obs.ndim == 1
        start = episode_start
        if single:
            obs = obs[None]
            if start is not None:
                start = np.asarray(start, dtype=bool).reshape(-1)[:1]
        if start is not None and np.all(start) and callable(getattr(self.policy, "reset", None)):
            try:
                self.policy.reset()
            except Exception as exc:  # noqa: BLE001 (a user's code can raise anything)
                raise RuntimeError(f"reset() raised {type(exc).__name__}: {exc}") from exc
        out = self.policy.predict(obs, state=state, episode_start=start, deterministic=deterministic)
        if not single or not isinstance(out, tuple) or len(out) != 2:
            return out
        from controllers.evaluation import BadAction

        action = np.asarray(out[0]) if not isinstance(out[0], np.ndarray) else out[0]
        if action.shape != (1, 3):
            raise BadAction(f"its action for a batch of one observation, shape (1, {obs.shape[1]}), has shape "
                            f"{action.shape}: expected (1, 3) (docs/benchmark.md, 'Your own controller')")
        return action[0], out[1]


def _agent_obs_width(agent: Any) -> int:
    """Width of the raw env observation an agent was trained on."""
    from auv_follow_env.layout import OBS_DIM

    try:
        probe = gym.make(agent.env_id, **(agent.env_kwargs or {}))
        width = int(probe.observation_space.shape[0])
        probe.close()
        return width
    except (gym.error.Error, ValueError, TypeError):
        return OBS_DIM


class IncompatiblePolicy(ValueError):
    """A policy that cannot run on a tier (e.g. an agent trained on the 20-field v1
    observation, on a 16-field v0 scenario)."""


def build_policy(spec: PolicySpec, run: str | None, env_id: str, task_spec: Any, obs_width: int) -> Any:
    """The policy object (SB3 ``predict`` protocol over raw observations of ``env_id``) of one
    run of ``spec`` (or of its controller)."""
    if spec.kind == "classical":
        from controllers import make_controller

        return make_controller(spec.controller, task_spec)
    if spec.kind == "external":
        cls = _import_external(spec.controller)
        try:
            obj = cls(task_spec)
        except Exception as exc:  # noqa: BLE001 (a user's constructor can raise anything)
            text = " ".join(str(exc).split())[:300]
            raise ValueError(f"policy {spec.label!r} on {env_id}: {spec.controller}(task_spec) raised "
                             f"{type(exc).__name__}" + (f": {text}" if text else "")) from exc
        return _BatchProtocol(obj, spec.label)
    from agents.training.loading import load_agent

    agent = load_agent(run, name=spec.label)
    width = _agent_obs_width(agent)
    if width > obs_width:
        raise IncompatiblePolicy(f"policy={spec.label!r} (run {run}) was trained on {width}-wide observations and "
                                 f"cannot run on {env_id} ({obs_width} fields)")
    policy = agent.raw_policy(env_id if width == obs_width else agent.env_id, {}) if agent.mode == "residual" \
        else agent
    return _ObsPrefix(policy, width) if width < obs_width else policy


#: a base controller without a target filter of its own -> the same control law on the target filter
#: that an ``estimator`` observation carries (what a residual on the base can copy from its input)
FILTERED_LAW: dict[str, str] = {"PROPOSED": "PROPOSED_KF"}


def _residual_settings(spec: PolicySpec) -> set[tuple[str, str] | None]:
    """{(base controller, observation)} over a learned method's runs (None: not a residual or unreadable)."""
    import yaml

    found: set[tuple[str, str] | None] = set()
    for r in spec.runs:
        try:
            cfg = yaml.safe_load(check_size(Path(r) / "config.yaml", "text").read_text()) or {}
        except (OSError, yaml.YAMLError, ValueError):
            found.add(None)
            continue
        run = cfg.get("run", {}) if isinstance(cfg, dict) else {}
        if run.get("mode") == "estimator":  # a learned estimator feeding its base controller's law
            found.add((str(run.get("controller")), "learned estimator"))
            continue
        if run.get("mode") != "residual":
            found.add(None)
            continue
        builder = cfg.get("observation") if isinstance(cfg.get("observation"), dict) else {}
        residual = cfg.get("residual") if isinstance(cfg.get("residual"), dict) else {}
        obs = builder.get("observation") or residual.get("observation") or run.get("observation") or "raw"
        found.add((str(run.get("controller")), str(obs)))
    return found


def residual_bases(specs: Iterable[PolicySpec]) -> dict[str, str]:
    """``{label: base controller}`` of the learned methods whose runs are residual agents on one
    base controller (read from each run's ``config.yaml``); methods mixing bases are left out."""
    out: dict[str, str] = {}
    for s in specs:
        if s.kind != "learned" or not s.runs:
            continue
        found = _residual_settings(s)
        bases = {f[0] for f in found if f is not None}
        if None not in found and len(bases) == 1:
            out[s.label] = bases.pop()
    return out


def residual_observations(specs: Iterable[PolicySpec]) -> dict[str, str]:
    """``{label: observation}`` ("raw" or "estimator") of the residual methods whose runs agree."""
    out: dict[str, str] = {}
    for s in specs:
        if s.kind != "learned" or not s.runs:
            continue
        found = _residual_settings(s)
        obs = {f[1] for f in found if f is not None}
        if None not in found and len(obs) == 1:
            out[s.label] = obs.pop()
    return out


def filtered_laws(specs: Iterable[PolicySpec]) -> dict[str, str]:
    """``{label: controller}`` for residual methods whose observation carries a target filter their
    base lacks: the same law on that filter (:data:`FILTERED_LAW`), the fair comparison for the
    information the observation carries in."""
    specs = list(specs)
    bases, obs = residual_bases(specs), residual_observations(specs)
    return {label: FILTERED_LAW[base] for label, base in bases.items()
            if obs.get(label) == "estimator" and base in FILTERED_LAW}
