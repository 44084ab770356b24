"""A learned target estimator for the Leader tiers: a GRU over the fix history that corrects the
generic IMM's estimate of the present reference point, trained by supervision, feeding the
classical tracking law (PROPOSED_IMM_DOB's law, gains and disturbance observer).

**Why a correction of the IMM.** On the Leader tiers the target switches between hidden
manoeuvre modes (docs/tiers.md) and a linear or IMM filter extrapolates the newest fix's speed and
turn rate over the packet's age (up to 7 s on Leader-Hard). What is left to learn is the part of
the present position those filters cannot know from one fix: where a survey leg ends, how long a
loiter or a sprint lasts, whether a fix is an outlier. The network sees, per control step, the
env's 20 observation fields and the IMM's present estimate (reference point, heading, speed, turn
rate), and returns a correction (dx, dy) of the reference point in the follower's body frame. With
a zero correction it *is* PROPOSED_IMM_DOB, so it starts at the generic classical.

**Training** (:func:`train_estimator`): episodes recorded on training seeds under
PROPOSED_IMM_DOB (closed loop), the true present reference point from the env's ``info``
(privileged: training only; deployment needs nothing but the observation). Loss: the mean
Euclidean error of the corrected reference point (the leaderboard's metric is the mean norm, so
the loss is the norm, not its square) over the steps where the IMM has a fix and the episode runs.
Truncated back-propagation through time over chunks of ``chunk`` steps, the hidden state carried
across chunks; Adam with a linear decay to 0. Every epoch the same loss is measured on
validation episodes (other training seeds); the learning curve goes to ``curve.csv``. The final
weights are the last epoch's (no choice on any seed set).

**Run directory** (loads with :func:`agents.training.load_agent` and scores in ``auv-follow
benchmark`` like a trained agent): ``model.zip`` (a torch file of tensors and plain values, read
with ``weights_only=True``), ``config.yaml`` (``run.algo: estimator``, ``run.mode: estimator``,
``run.controller: PROPOSED_IMM_DOB``, the data seeds and the settings), ``curve.csv``.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from auv_follow_env.layout import OBS_DIM_V1
from auv_follow_env.metrics import true_reference_body
from auv_follow_env.params import TaskSpec
from controllers.estimator import TargetEstimate, TargetEstimator, _copy_estimate
from controllers.hierarchical import reference_point

__all__ = ["MODEL_FORMAT", "BASE_CONTROLLER", "EstimatorSettings", "LearnedEstimator", "EstimatorAgent",
           "features", "record_episodes", "train_estimator", "load_estimator_agent", "make_controller_from"]

MODEL_FORMAT = "auv-follow/learned-estimator/v1"
BASE_CONTROLLER = "PROPOSED_IMM_DOB"
N_FEATURES = OBS_DIM_V1 + 7


def features(obs: np.ndarray, est: TargetEstimate, spec: TaskSpec) -> np.ndarray:
    """The network's input per env (N, 27): the 20 observation fields, then the IMM's present
    reference point in the body frame (x, y) [m], cos / sin of its heading relative to the
    follower, its speed [m/s] and turn rate [rad/s], and whether it has a fix (1 / 0)."""
    xr, yr, _ = reference_point(est.rel_x, est.rel_y, est.rel_psi, spec.p_d, spec.psi_d)
    v = est.valid
    extra = np.stack([np.where(v, xr, 0.0), np.where(v, yr, 0.0), np.where(v, np.cos(est.rel_psi), 1.0),
                      np.where(v, np.sin(est.rel_psi), 0.0), np.where(v, est.u, 0.0), np.where(v, est.r, 0.0),
                      v.astype(np.float64)], axis=-1)
    return np.concatenate([np.asarray(obs, dtype=np.float64), extra], axis=-1)


def _network(hidden: int):
    import torch
    from torch import nn

    class Net(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.gru = nn.GRU(N_FEATURES, hidden)
            self.head = nn.Sequential(nn.Linear(hidden + N_FEATURES, 64), nn.Tanh(), nn.Linear(64, 2))
            with torch.no_grad():  # start at a zero correction: the generic IMM
                self.head[2].weight.mul_(0.01)
                self.head[2].bias.zero_()

        def forward(self, x, h):  # x (T, B, F) normalised, h (1, B, H)
            y, h = self.gru(x, h)
            return self.head(torch.cat([y, x], dim=-1)), h

    return Net()


@dataclass(frozen=True)
class EstimatorSettings:
    """Training settings (defaults: what the committed Leader runs used)."""

    hidden: int = 64  #: GRU units
    epochs: int = 20  #: passes over the training episodes
    batch: int = 512  #: episodes per minibatch
    chunk: int = 100  #: steps per truncated back-propagation window
    lr: float = 2e-3  #: Adam's initial learning rate (linear decay to 0)
    torch_threads: int = 1

    def __post_init__(self) -> None:
        for name in ("hidden", "epochs", "batch", "chunk", "torch_threads"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}={v!r} is invalid: must be a whole number >= 1")
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not 0 < self.lr < 1:
            raise ValueError(f"lr={self.lr!r} is invalid: must be a number in (0, 1)")


def _imm(spec: TaskSpec) -> TargetEstimator:
    from controllers import make_controller

    return make_controller(BASE_CONTROLLER, spec).estimator


def record_episodes(env_id: str, first_seed: int, n: int, *, progress: bool = False) -> dict[str, np.ndarray]:
    """``n`` episodes (seeds ``first_seed`` ...) under PROPOSED_IMM_DOB: the network's inputs
    (T, n, 27) float32, the target correction (T, n, 2) float32 (true minus IMM reference point,
    body frame [m]) and the mask (T, n) of steps where the episode runs and the IMM has a fix.

    Raises:
        ValueError: a test seed (these are training data) or a non-Leader env.
    """
    import gymnasium as gym
    from tqdm.auto import tqdm

    from auv_follow_env.tiers import check_training_seeds
    from controllers import make_controller

    check_training_seeds(range(int(first_seed), int(first_seed) + int(n)))
    venv = gym.make_vec(env_id, num_envs=int(n), vectorization_mode="vector_entry_point")
    spec = venv.unwrapped.task_spec
    if getattr(spec, "tier", None) is None or not str(spec.tier).startswith("Leader"):
        venv.close()
        raise ValueError(f"env_id={env_id!r} is invalid: the learned estimator is for the Leader tiers")
    ctrl, imm = make_controller(BASE_CONTROLLER, spec), _imm(spec)
    obs, info = venv.reset(seed=int(first_seed))
    T = int(spec.n_steps)
    X = np.zeros((T, n, N_FEATURES), np.float32)
    Y = np.zeros((T, n, 2), np.float32)
    M = np.zeros((T, n), bool)
    running, start = np.ones(n, bool), np.ones(n, bool)
    for k in tqdm(range(T), desc=f"record {env_id}", disable=not progress, leave=False):
        est = imm.step(obs, start, with_cov=False)
        X[k] = features(obs, est, spec)
        bx, by = true_reference_body(info)
        Y[k, :, 0] = bx - X[k, :, OBS_DIM_V1]
        Y[k, :, 1] = by - X[k, :, OBS_DIM_V1 + 1]
        M[k] = running & est.valid
        a, _ = ctrl.predict(obs, episode_start=start)
        start[:] = False
        obs, _, term, trunc, info = venv.step(a)
        running &= ~(term | trunc)
    venv.close()
    return {"X": X, "Y": Y, "M": M}


def _loss(net, X, Y, M, h, torch):
    pred, h = net(X, h)
    err = torch.sqrt(((pred - Y) ** 2).sum(-1) + 1e-6)
    m = M.float()
    return (err * m).sum(), m.sum(), h


def _evaluate(net, data, mean, std, torch, batch: int = 512) -> float:
    """Mean corrected-reference error [m] over the masked steps of ``data``."""
    tot, cnt = 0.0, 0.0
    with torch.no_grad():
        for b in range(0, data["X"].shape[1], batch):
            X = torch.from_numpy((data["X"][:, b:b + batch] - mean) / std)
            s, c, _ = _loss(net, X, torch.from_numpy(data["Y"][:, b:b + batch]),
                            torch.from_numpy(data["M"][:, b:b + batch]), None, torch)
            tot, cnt = tot + float(s), cnt + float(c)
    return tot / max(cnt, 1.0)


def _imm_error(data) -> float:
    e = np.hypot(data["Y"][..., 0], data["Y"][..., 1])
    return float(e[data["M"]].mean())


def train_estimator(env_id: str, out_dir: str | Path, *, seed: int = 0, n_train: int = 4096, n_val: int = 256,
                    settings: EstimatorSettings | None = None, progress: bool = True) -> Path:
    """Record, train and write one learned estimator run (see the module docstring).

    Data seeds (training seeds only): training episodes ``100_000 + seed * 10_000 + [0, n_train)``,
    validation episodes ``900_000 + [0, n_val)`` (the same for every seed); torch seeded with ``seed``.

    Raises:
        ValueError: a bad argument (named), or more than 10,000 training episodes per seed.
    """
    import torch
    from tqdm.auto import tqdm

    from agents.training.rundir import _write_yaml, versions

    st = settings or EstimatorSettings()
    for name, v, hi in (("seed", seed, 9), ("n_train", n_train, 10_000), ("n_val", n_val, 10_000)):
        if isinstance(v, bool) or not isinstance(v, int) or not (0 if name == "seed" else 1) <= v <= hi:
            raise ValueError(f"{name}={v!r} is invalid: must be a whole number in [{0 if name == 'seed' else 1}, {hi}]")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    first = 100_000 + seed * 10_000
    train = record_episodes(env_id, first, n_train, progress=progress)
    val = record_episodes(env_id, 900_000, n_val, progress=progress)
    t_rec = time.perf_counter() - t0
    sel = train["M"]
    mean = train["X"][sel].mean(0).astype(np.float32)
    std = (train["X"][sel].std(0) + 1e-3).astype(np.float32)
    torch.manual_seed(seed)
    torch.set_num_threads(st.torch_threads)
    net = _network(st.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=st.lr)
    T = train["X"].shape[0]
    n_batches = math.ceil(n_train / st.batch)
    total = st.epochs * n_batches * math.ceil(T / st.chunk)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: max(0.0, 1.0 - i / total))
    rng = np.random.default_rng(seed)
    Xn = (train["X"] - mean) / std
    curve = [{"epoch": 0, "train_m": float("nan"), "val_m": _evaluate(net, val, mean, std, torch),
              "val_imm_m": _imm_error(val)}]
    bar = tqdm(range(st.epochs), desc=f"train estimator seed {seed}", disable=not progress)
    for ep in bar:
        perm = rng.permutation(n_train)
        tot, cnt = 0.0, 0.0
        for b in range(n_batches):
            idx = np.sort(perm[b * st.batch:(b + 1) * st.batch])
            X = torch.from_numpy(Xn[:, idx])
            Y, M = torch.from_numpy(train["Y"][:, idx]), torch.from_numpy(train["M"][:, idx])
            h = None
            for c0 in range(0, T, st.chunk):
                s, c, h = _loss(net, X[c0:c0 + st.chunk], Y[c0:c0 + st.chunk], M[c0:c0 + st.chunk], h, torch)
                h = h.detach()
                if float(c) > 0:
                    opt.zero_grad()
                    (s / c).backward()
                    torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
                    opt.step()
                sched.step()
                tot, cnt = tot + float(s.detach()), cnt + float(c)
        curve.append({"epoch": ep + 1, "train_m": tot / max(cnt, 1.0),
                      "val_m": _evaluate(net, val, mean, std, torch), "val_imm_m": curve[0]["val_imm_m"]})
        bar.set_postfix(train=f"{curve[-1]['train_m']:.3f}", val=f"{curve[-1]['val_m']:.3f}")
    torch.save({"format": MODEL_FORMAT, "hidden": st.hidden, "n_features": N_FEATURES,
                "feat_mean": torch.from_numpy(mean), "feat_std": torch.from_numpy(std),
                "state_dict": net.state_dict()}, out / "model.zip")
    with open(out / "curve.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(curve[0]))
        w.writeheader()
        w.writerows(curve)
    config = {"run": {"algo": "estimator", "mode": "estimator", "env_id": env_id, "env_kwargs": {},
                      "controller": BASE_CONTROLLER, "observation": "estimator", "seed": seed,
                      "run_name": out.name},
              "data": {"train_seeds": [first, first + n_train - 1], "val_seeds": [900_000, 900_000 + n_val - 1]},
              "settings": {k: getattr(st, k) for k in ("hidden", "epochs", "batch", "chunk", "lr", "torch_threads")},
              "result": {"val_m": curve[-1]["val_m"], "val_imm_m": curve[0]["val_imm_m"],
                         "record_seconds": round(t_rec, 1),
                         "train_seconds": round(time.perf_counter() - t0 - t_rec, 1)},
              "versions": versions()}
    _write_yaml(out / "config.yaml", config)
    return out


class LearnedEstimator(TargetEstimator):
    """The IMM of PROPOSED_IMM_DOB with the learned correction of its reference point (a
    :class:`TargetEstimator`, so the hierarchical law takes it as its estimator). The GRU's
    hidden state is per env, reset at an episode start; a peek (``commit=False``) leaves it as it was."""

    def __init__(self, spec: TaskSpec, weights: dict[str, Any]) -> None:
        import torch

        imm = _imm(spec)
        super().__init__(spec, imm.config)
        self._torch = torch
        self.net = _network(int(weights["hidden"]))
        self.net.load_state_dict(weights["state_dict"])
        self.net.eval()
        self._mean = weights["feat_mean"].numpy().astype(np.float64)
        self._std = weights["feat_std"].numpy().astype(np.float64)
        self._h = None
        self._lpeek = None

    def reset(self) -> None:
        super().reset()
        self._h, self._lpeek = None, None

    def step(self, observation: np.ndarray, reset_mask: np.ndarray | None = None, *, commit: bool = True,
             with_cov: bool = True, copy: bool = True) -> TargetEstimate:
        """:meth:`TargetEstimator.step` plus the learned correction (the result is always a new
        estimate, whatever ``copy``)."""
        torch = self._torch
        fresh = self._s is None
        est = super().step(observation, reset_mask, commit=commit, with_cov=with_cov, copy=False)  # (copied below)
        obs = np.atleast_2d(np.asarray(observation, dtype=np.float64))
        n = obs.shape[0]
        mask = np.zeros(n, bool) if reset_mask is None else np.asarray(reset_mask, bool).reshape(n)
        key = (obs.tobytes(), mask.tobytes())
        if commit and self._lpeek is not None and self._lpeek[0] == key:
            h, delta = self._lpeek[1], self._lpeek[2]
        else:
            h0 = self._h
            if fresh or h0 is None or h0.shape[1] != n:
                h0 = torch.zeros(1, n, self.net.gru.hidden_size)
            if mask.any():
                h0 = h0.clone()
                h0[:, torch.from_numpy(mask)] = 0.0
            x = (features(obs, est, self.spec) - self._mean) / self._std
            with torch.no_grad():
                y, h = self.net(torch.from_numpy(x.astype(np.float32))[None], h0)
            delta = y[0].numpy().astype(np.float64)
        if commit:
            self._h, self._lpeek = h, None
        else:
            self._lpeek = (key, h, delta)
        out = _copy_estimate(est)
        v = out.valid
        out.rel_x = np.where(v, out.rel_x + delta[:, 0], out.rel_x)
        out.rel_y = np.where(v, out.rel_y + delta[:, 1], out.rel_y)
        return out


def make_controller_from(spec: TaskSpec, weights: dict[str, Any], name: str = "learned estimator"):
    """PROPOSED_IMM_DOB's law, gains and disturbance observer on :class:`LearnedEstimator`."""
    from controllers import make_controller

    base = make_controller(BASE_CONTROLLER, spec)
    base.estimator = LearnedEstimator(spec, weights)
    base.name = name
    return base


class EstimatorAgent:
    """A learned-estimator run as a policy (SB3's ``predict`` over raw observations): the tracking
    law of PROPOSED_IMM_DOB on the learned estimator, built per env id on first use."""

    env_wrapper = None  #: it reads raw observations: no wrapper (as a bppo agent)

    def __init__(self, weights: dict[str, Any], config: dict[str, Any], name: str | None = None) -> None:
        self.weights, self.config = weights, config
        run = config["run"]
        self.env_id, self.env_kwargs, self.mode = run["env_id"], dict(run.get("env_kwargs") or {}), "estimator"
        self.residual, self.stats = None, None
        self.name = name or f"Learned estimator on {BASE_CONTROLLER}"
        self._ctrl = None

    def raw_policy(self, env_id: str | None = None, env_kwargs: dict | None = None) -> Any:
        return self

    def controller(self):
        """The controller (PROPOSED_IMM_DOB's law on the learned estimator) for this run's env id."""
        if self._ctrl is None:
            import gymnasium as gym

            env = gym.make(self.env_id, **self.env_kwargs)
            spec = env.unwrapped.task_spec
            env.close()
            self._ctrl = make_controller_from(spec, self.weights, self.name)
        return self._ctrl

    def reference(self, observation) -> np.ndarray:
        return self.controller().reference(observation)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        return self.controller().predict(observation, state=state, episode_start=episode_start,
                                          deterministic=deterministic)


def load_estimator_agent(model_path: str | Path, config: dict[str, Any], name: str | None = None) -> EstimatorAgent:
    """The agent of a learned-estimator run's ``model.zip``.

    Raises:
        ValueError: the file is not a learned-estimator model (names it).
    """

    from agents.training.torch_files import load_torch_file

    w = load_torch_file(model_path, "a learned-estimator model")
    if not isinstance(w, dict) or w.get("format") != MODEL_FORMAT:
        raise ValueError(f"{model_path} is not a learned-estimator model (format "
                         f"{w.get('format') if isinstance(w, dict) else None!r}, expected {MODEL_FORMAT!r})")
    return EstimatorAgent(w, config, name=name)
