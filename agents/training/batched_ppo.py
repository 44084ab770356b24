"""Batched PPO in plain torch (CleanRL-style) on the native vector env: the training path
``algo="bppo"`` of :func:`agents.training.train` (``python -m agents.cli train --algo bppo``).

Why not SB3 or a library: SB3's PPO steps the env through its ``VecEnv`` protocol with per-env
Python bookkeeping and the residual wrapper ran the base controller one env at a time;
we measured a lean batched PPO in plain torch at 3.3-5.1x the default PPO's env-steps
per CPU-second and skrl 2.1.1 at 2.8x (skrl is not installed here). So this module is about
400 lines: rollouts of ``n_steps`` on N envs (:class:`agents.training.batched_env.BatchedTrainEnv`:
one kernel call and one batched base-controller call per step), GAE, clipped PPO updates on
minibatches of the whole rollout.

**Settings** (``agents/training/hyperparams/bppo.yml``, overridable with ``--hp``): N = ``n_envs``
(512), ``n_steps`` (32: 16,384 samples per update), ``gamma`` = 0.995, i.e. a horizon
1 / (1 - gamma) = 200 steps = 10 s at dt = 0.05 s, longer than a packet cycle on Hard
(4-7 s), so the value of waiting for the next packet is inside the horizon (SB3's default
0.98 covered 2.5 s). Observation and reward normalisation as SB3's ``VecNormalize``
(running mean / variance; the reward divided by the running std of the discounted return),
with ``normalize=dict(...)``'s ``clip_obs``, ``clip_reward``, ``epsilon`` and ``gamma`` honoured as SB3
does (defaults 10, 10, 1e-8 and the algorithm's gamma).
``lr_schedule``: ``linear`` (the default: decays to 0 at the budget, as CleanRL's ``anneal_lr``;
the policy's std shrinks over training, and at a constant rate the late updates grew until
the evaluation curves turned back up) or ``constant`` (what the first committed runs used; every
run records its schedule under ``training:`` in ``config.yaml``).

**Normalisers that forget.** ``obs_norm_window`` and ``reward_norm_window`` (samples; 1,000,000
by default, 0 = SB3's never-forgetting statistics) cap the count of the running statistics, so a
new batch of b samples weighs b / (window + b) and samples older than about a window fade out.
Without them the first few million steps' metre-sized errors set both scales for the whole run:
the return std stayed at 200-480 while the late episodes' returns were a thousand times smaller
(a step's normalised reward about -3e-4, the value loss 3e-6), and the estimated reference error's
std at 1-2 m for a 0.02 m steady error. A fixed physical reward scale was the alternative; the
window needs no per-tier constant and follows the policy as it improves. Both windows are
recorded in ``config.yaml`` (``training:``) and the observation window in ``vecnormalize.json``.

**Reference errors scaled, not centred** (``obs_error_norm``: ``scaled``, the default from scratch,
or ``centered``, what every run before this default used and bppo.yml's ``residual`` section keeps,
since no residual was measured scaled). A forgetting mean has a drift mode: the
running mean of the reference-error fields (``ref_dx``, ``ref_dy``, ``est_ref_dx``, ``est_ref_dy``;
zero = on the reference) follows the policy's own steady offset, so an offset the policy settles
into soon reads as zero error. One Medium run drifted so from 0.31 m to 1.0 m: its statistics ended
with est_ref_dx and est_ref_dy means of +0.87 and -0.42 m (the two other seeds: 0.03-0.05 m, and
PROPOSED_KF_DOB's own closed loop about 0.002 m). ``scaled`` holds those fields' mean at 0 and
divides them by their running root mean square (their "variance" in ``vecnormalize.json`` is the
mean square, their mean 0; evaluation applies the same file unchanged). ``config.yaml`` records
the choice and the columns under ``training:``.

**Smoothness** (both off by default): ``action_rate_coef`` c adds -c ||a_k - a_(k-1)||^2 (action
units, none at an episode's first step) to the training reward (the env's own reward and every
score are unchanged); ``action_filter`` alpha in (0, 1) makes the agent's action the state of a
first-order low-pass, ``u_k = u_(k-1) + alpha (a_k - u_(k-1))``, with ``u_(k-1)`` appended to the
observation (so the policy stays Markov; the loaded agent filters the same way). ``progress.csv``
logs the mean |dF_u| per step of the executed actions. ``heading_coef`` c adds -c (1 - cos(psi_ref -
psi)) with the true present reference heading (the env's reward scores position only, so a policy
is free to spin: the first smooth runs held the yaw moment at its limit and turned at 7 rad/s;
the term, privileged like the env's own reward, asks for the paper's heading). ``bounds_loss_coef``
c adds c sum_j relu(|mu_j| - 1)^2 to the PPO loss (mu: the policy's mean action): a mean beyond the
env's box [-1, 1] is clipped by the env, so moving it changes nothing the env sees and PPO's
gradient cannot bring it back; longer Medium and Hard runs ended with the yaw moment's mean at
1.3-1.6 (std 0.05), spinning at 5.8 rad/s whatever the heading term asked. ``yaw_rate_coef`` c
adds -c r^2 with the follower's own yaw rate r [rad/s] (field ``r`` of the observation): a
penalty that grows with the spin itself, on every step.

**Residuals: use ``gae_lambda=1``.** With lambda < 1 the advantage bootstraps from the critic's
value of the *next* state, which the action moves; early on the critic is poor and its errors,
not the return, set the gradient. A residual's true signal is weak (the base already tracks), so
that bias wins: residual runs with lambda = 0.95 (or 0.9) drifted steadily worse on their own
training return (paper's PROPOSED on Medium: 0.128 m -> 0.50 m in 3 M steps), with lambda = 1
(Monte Carlo returns, gamma = 0.98) the same run did not (0.128 -> 0.102 m, noisily).
Gaussian policy with a state-independent log std; the mean layer starts at 0.01 x the usual
scale, so a residual agent starts at (almost) the base controller.

**Options** in ``policy_kwargs``: ``net_arch`` (hidden sizes: one list for the actor and the
critic, or SB3's ``dict(pi=[...], vf=[...])`` for each its own; at most 16 layers of 8192),
``activation`` (tanh/relu), ``log_std_init`` (in [-5, 2]), ``linear_skip`` (the actor's mean
adds a linear map of its input, initialised at zero: a near-linear law such as a PD on the estimated error is one layer
away), ``recurrent`` (a GRU trunk of ``gru_size`` units shared by actor and
critic, trained on whole rollout sequences per env with the state reset at episode
starts), ``privileged_critic`` (asymmetric critic: the critic also sees the *true* present
reference point relative to the follower, from the env's ``info["true_reference"]`` and
``info["follower_pose"]``: dx, dy in the body frame, cos/sin of the heading error; the
actor never does, and evaluation needs no privileged input), ``squash`` (a tanh-squashed
Gaussian: the env gets tanh(a) for a ~ N(mu, std), so the action stays inside the box without the
env's clipping and a mean far out still moves the action a little; the buffer keeps a, and the
tanh's Jacobian cancels in PPO's ratio; ``predict`` returns tanh(mu)).

**Distillation** (``teacher``, ``teacher_link``, ``distill_steps``): for the first
``distill_steps`` env steps the student is trained by DAgger, not PPO. A scripted controller
(the teacher, batched) labels every state; the env executes the teacher's action with
probability :func:`mix_probability` (1 falling linearly to 0 at half of ``distill_steps``) and
the student's mean otherwise, so the student is finally labelled on the states it reaches
itself. The actor's mean is regressed onto the labels (MSE, logged as ``policy_loss``) and the
critic onto the returns of the executed actions. ``teacher_link="perfect"`` gives the teacher
the present target exactly (:func:`auv_follow_env.perfect_link.perfect_link_observation`: privileged, training
only); ``"real"`` the same link as the student. The teacher's disturbance observer is told the
force the env was commanded, not the teacher's own. PPO then continues from the student.

**Divergence.** Every action, loss and (after each update) parameter is checked: at the first
NaN or infinite one training stops, no ``model.zip`` is written (checkpoints from before stay),
``config.yaml`` records ``result.failed`` and :func:`agents.training.train` raises
:class:`agents.training.TrainingFailed` (``auv-follow train``: one line, exit code 1).

**Threads and speed.** The env steps on numba's serial kernel (``parallel=False``) and torch
uses ``torch_threads`` threads (default 2, the cores of the machines we measure on; set 1 when
several trainings share the cores, as ``auv-follow sweep`` does per CPU of a trial). The profile
(``python -m experiments.bench_train``, which reports the split from ``result.phase_seconds`` in
``config.yaml``) put two thirds of the wall clock in the PPO update and 3 % in the physics, so
the update is where the cores go: torch's threads split its matrix products, and the ``tanh``
layers use numpy's SIMD ``tanh`` (torch 2.13's CPU ``tanh`` took a third of an update on its
own). Each epoch gathers its shuffled samples once; the minibatches are slices of it.

**Run directory** (the contract of :mod:`agents.training`): ``config.yaml`` (with ``steps_done``
and ``train_seconds``, refreshed at every checkpoint and evaluation), ``model.zip`` (a torch
file of tensors and plain values, loaded with ``weights_only=True``: loading runs no pickled
code), ``vecnormalize.json`` (:mod:`agents.training.obs_stats`), ``checkpoints/model_<steps>_steps.zip``
with ``model_vecnormalize_<steps>_steps.json``, ``eval.csv`` (the learning curve: evaluations
on ``n_eval_seeds`` fixed seeds from ``eval_seed`` (990,000), none of them a training env's seed),
``progress.csv`` (per update: losses, episode
statistics, throughput) and ``tb/`` (TensorBoard, if installed).
"""

from __future__ import annotations

import csv
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agents.training.obs_stats import ObsStats, read_obs_stats, write_obs_stats
from auv_follow_env.metrics import true_reference_body

__all__ = ["BatchedPPO", "BatchedAgent", "train_bppo", "load_bppo_agent", "MODEL_FORMAT", "POLICY_DEFAULTS"]

MODEL_FORMAT = "auv-follow/batched-ppo/v1"
POLICY_DEFAULTS: dict[str, Any] = {"net_arch": [64, 64], "activation": "tanh", "log_std_init": -1.0,
                                   "recurrent": False, "gru_size": 64, "privileged_critic": False,
                                   "linear_skip": False, "squash": False}
LR_SCHEDULES = ("constant", "linear")
TEACHER_LINKS = ("perfect", "real")
PRIV_DIM = 4
CLIP_OBS = 10.0
CLIP_REWARD = 10.0
EPS = 1e-8


#: ``obs_error_norm``: the reference-error fields (zero = on the reference) centred on their running
#: mean as every other field (SB3's), or only scaled by their running root mean square (zero stays zero)
OBS_ERROR_NORMS = ("centered", "scaled")
OBS_ERROR_NORM_DEFAULT = "scaled"  #: from scratch (bppo.yml's residual section keeps "centered")


class BatchedPPO:
    """The hyperparameters of the batched PPO (the constructor's signature is what
    :func:`agents.training.check_hyperparams` validates ``--hp`` keys against)."""

    def __init__(self, policy: str = "MlpPolicy", n_steps: int = 32, batch_size: int = 4096, n_epochs: int = 5,
                 gamma: float = 0.995, gae_lambda: float = 0.95, learning_rate: float = 3e-4,
                 clip_range: float = 0.2, ent_coef: float = 0.0, vf_coef: float = 0.5, max_grad_norm: float = 0.5,
                 target_kl: float | None = None, policy_kwargs: dict | None = None, torch_threads: int = 2,
                 random_phase: bool = True, n_eval_seeds: int = 32, lr_schedule: str = "linear",
                 obs_norm_window: int = 1_000_000, reward_norm_window: int = 1_000_000, teacher: str | None = None,
                 teacher_link: str = "perfect", distill_steps: int = 0, action_rate_coef: float = 0.0,
                 action_filter: float = 1.0, heading_coef: float = 0.0, bounds_loss_coef: float = 0.0,
                 yaw_rate_coef: float = 0.0, yaw_from: str | None = None,
                 obs_error_norm: str = OBS_ERROR_NORM_DEFAULT) -> None:
        self.__dict__.update({k: v for k, v in locals().items() if k != "self"})


#: bounds of the policy options: wider or deeper networks, or a std outside these, are refused before any work
MAX_HIDDEN = 8192  #: units of one hidden layer (and of the GRU)
MAX_LAYERS = 16  #: hidden layers of the actor or the critic
LOG_STD_MIN = -5.0  #: training clamps the policy's log std here (a lower initial value would never move)
LOG_STD_INIT_RANGE = (LOG_STD_MIN, 2.0)  #: allowed log_std_init (std e^-5 = 0.007 to e^2 = 7.4 in action units)
MAX_ROLLOUT_SAMPLES = 2 ** 22  #: n_steps x n_envs: samples held in memory per update (default 32 x 512 = 16,384)


def whole_number(name: str, v: Any, lo: int, hi: float = math.inf) -> int:
    """The one rule for integer settings: an integer, or a float (or a numeric string, as YAML
    1.1 reads ``1e6``) that is a whole number, such as ``1.0e+6``, within [lo, hi]; never a bool.
    Raises ValueError naming ``name``, the value and the range."""
    x = v
    if isinstance(x, str):
        try:
            x = float(x)
        except ValueError:
            pass
    ok = isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))
    if ok and isinstance(x, (float, np.floating)):
        ok = math.isfinite(x) and float(x).is_integer()
    if ok:
        x = int(x)
        ok = lo <= x <= hi
    if not ok:
        rng = f">= {lo}" if hi == math.inf else f"in [{lo}, {hi:g}]"
        raise ValueError(f"{name}={v!r} is invalid: must be a whole number {rng}")
    return x


def _real(name: str, v: Any, lo: float, hi: float) -> float:
    """A finite number in [lo, hi] (not a bool); raises ValueError naming ``name`` and the value."""
    x = v
    if isinstance(x, str):
        try:
            x = float(x)
        except ValueError:
            pass
    ok = isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))
    if ok:
        try:
            x = float(x)
        except OverflowError:
            ok = False
    if not (ok and math.isfinite(x) and lo <= x <= hi):
        raise ValueError(f"{name}={v!r} is invalid: must be a finite number in [{lo:g}, {hi:g}]")
    return x


def _sizes(name: str, v: Any) -> list[int]:
    if not isinstance(v, (list, tuple)) or len(v) > MAX_LAYERS:
        raise ValueError(f"{name}={v!r} is invalid: must be a list of at most {MAX_LAYERS} hidden sizes (whole "
                         f"numbers in [1, {MAX_HIDDEN}])")
    try:
        return [whole_number(name, h, 1, MAX_HIDDEN) for h in v]
    except ValueError:
        raise ValueError(f"{name}={v!r} is invalid: must be a list of at most {MAX_LAYERS} hidden sizes (whole "
                         f"numbers in [1, {MAX_HIDDEN}])") from None


def _policy_kwargs(pk: dict | None) -> dict[str, Any]:
    """The policy options merged over :data:`POLICY_DEFAULTS`, checked and normalised:
    ``net_arch`` is a list of hidden sizes (actor and critic alike) or SB3's
    ``dict(pi=[...], vf=[...])`` (the actor's and the critic's, both keys required)."""
    if pk is not None and not isinstance(pk, dict):
        raise ValueError(f"policy_kwargs={pk!r} is invalid: must be a dict")
    out = dict(POLICY_DEFAULTS)
    out.update(pk or {})
    bad = sorted(map(str, set(out) - set(POLICY_DEFAULTS)))
    if bad:
        raise ValueError(f"policy_kwargs has unknown key(s) {bad}: valid keys are {list(POLICY_DEFAULTS)}")
    arch = out["net_arch"]
    if isinstance(arch, dict):  # SB3 style: separate actor (pi) and critic (vf) sizes
        keys = set(map(str, arch))
        if keys != {"pi", "vf"}:
            raise ValueError(f"policy_kwargs net_arch={arch!r} is invalid: a dict needs exactly the keys 'pi' (actor) "
                             f"and 'vf' (critic), got {sorted(keys)}; or give one list for both")
        out["net_arch"] = {"pi": _sizes("policy_kwargs net_arch['pi']", arch["pi"]),
                           "vf": _sizes("policy_kwargs net_arch['vf']", arch["vf"])}
    else:
        out["net_arch"] = _sizes("policy_kwargs net_arch", arch)
    if out["activation"] not in ("tanh", "relu"):
        raise ValueError(f"policy_kwargs activation={out['activation']!r} is invalid: must be 'tanh' or 'relu'")
    for key in ("recurrent", "privileged_critic", "linear_skip", "squash"):
        if not isinstance(out[key], bool):
            raise ValueError(f"policy_kwargs {key}={out[key]!r} is invalid: must be True or False")
    out["gru_size"] = whole_number("policy_kwargs gru_size", out["gru_size"], 1, MAX_HIDDEN)
    lo, hi = LOG_STD_INIT_RANGE
    try:
        out["log_std_init"] = _real("policy_kwargs log_std_init", out["log_std_init"], lo, hi)
    except ValueError as exc:
        raise ValueError(f"{exc} (the policy's initial std is exp(log_std_init) in action units; training clamps "
                         f"the log std at {LOG_STD_MIN:g})") from None
    return out


def _arch(pk: dict[str, Any], part: str) -> list[int]:
    """Hidden sizes of the actor (``part="pi"``) or the critic (``"vf"``)."""
    arch = pk["net_arch"]
    return list(arch[part]) if isinstance(arch, dict) else list(arch)


def check_bppo_hyperparams(hp: dict[str, Any], n_envs: int | None = None) -> None:
    """The checks :func:`agents.training.check_hyperparams` cannot do for bppo (raises ValueError);
    with ``n_envs``, also the memory of one rollout (n_steps x n_envs samples)."""
    _policy_kwargs(hp.get("policy_kwargs"))
    whole_number("hyperparameter torch_threads", hp.get("torch_threads", 1), 1, 64)
    whole_number("hyperparameter n_eval_seeds", hp.get("n_eval_seeds", 32), 1, 10_000)
    sched = hp.get("lr_schedule", "constant")
    if sched not in LR_SCHEDULES:
        raise ValueError(f"hyperparameter lr_schedule={sched!r} is invalid: must be one of {list(LR_SCHEDULES)}")
    try:
        whole_number("hyperparameter obs_norm_window", hp.get("obs_norm_window", 0), 0)
        whole_number("hyperparameter reward_norm_window", hp.get("reward_norm_window", 0), 0)
    except ValueError as exc:
        raise ValueError(f"{exc} (samples; 0 = never forget)") from None
    if hp.get("obs_error_norm", OBS_ERROR_NORM_DEFAULT) not in OBS_ERROR_NORMS:
        raise ValueError(f"hyperparameter obs_error_norm={hp.get('obs_error_norm')!r} is invalid: must be one of "
                         f"{list(OBS_ERROR_NORMS)} (how the reference-error fields are normalised)")
    _real("hyperparameter action_rate_coef", hp.get("action_rate_coef", 0.0), 0.0, math.inf)
    _real("hyperparameter heading_coef", hp.get("heading_coef", 0.0), 0.0, math.inf)
    _real("hyperparameter bounds_loss_coef", hp.get("bounds_loss_coef", 0.0), 0.0, math.inf)
    _real("hyperparameter yaw_rate_coef", hp.get("yaw_rate_coef", 0.0), 0.0, math.inf)
    from agents.training.batched_obs import check_action_filter

    try:
        check_action_filter(hp.get("action_filter", 1.0))
    except ValueError as exc:
        raise ValueError(f"hyperparameter {exc}") from None
    yaw_from = hp.get("yaw_from")
    if yaw_from is not None:
        from controllers import ALL_CONTROLLERS

        if not isinstance(yaw_from, str) or yaw_from not in ALL_CONTROLLERS:
            raise ValueError(f"hyperparameter yaw_from={yaw_from!r} is invalid: must be null or one of "
                             f"{list(ALL_CONTROLLERS)} (the controller whose yaw moment replaces the agent's)")
    if not isinstance(hp.get("random_phase", True), bool):
        raise ValueError(f"hyperparameter random_phase={hp.get('random_phase')!r} is invalid: must be true or false")
    _check_teacher(hp)
    if hp.get("policy", "MlpPolicy") != "MlpPolicy":
        raise ValueError(f"hyperparameter policy={hp.get('policy')!r} is invalid for bppo: only 'MlpPolicy' "
                         "(use policy_kwargs recurrent=True for a GRU)")
    if n_envs is not None:
        t = whole_number("hyperparameter n_steps", hp.get("n_steps", 32), 1)
        if t * int(n_envs) > MAX_ROLLOUT_SAMPLES:
            raise ValueError(f"hyperparameter n_steps={hp.get('n_steps')!r} is invalid with n_envs={n_envs}: a rollout "
                             f"of n_steps x n_envs = {t * int(n_envs):,} samples is held in memory; at most "
                             f"{MAX_ROLLOUT_SAMPLES:,} allowed")


def _check_teacher(hp: dict[str, Any], mode: str | None = None, env_id: str | None = None) -> None:
    """The distillation options (module docstring, "Distillation"); raises ValueError."""
    from controllers import ALL_CONTROLLERS

    teacher, link, n = hp.get("teacher"), hp.get("teacher_link", "perfect"), hp.get("distill_steps", 0)
    if teacher is not None and (not isinstance(teacher, str) or teacher not in ALL_CONTROLLERS):
        raise ValueError(f"hyperparameter teacher={teacher!r} is invalid: must be None or one of "
                         f"{list(ALL_CONTROLLERS)}")
    if not isinstance(link, str) or link not in TEACHER_LINKS:
        raise ValueError(f"hyperparameter teacher_link={link!r} is invalid: must be one of {list(TEACHER_LINKS)}")
    n = whole_number("hyperparameter distill_steps", n, 0)
    if n > 0 and teacher is None:
        raise ValueError(f"hyperparameter distill_steps={n} needs a teacher (hyperparameter teacher=<controller>)")
    if teacher is not None and n == 0:  # the teacher would never be asked: refuse rather than record it
        raise ValueError(f"hyperparameter teacher={teacher!r} needs distill_steps > 0 (the env steps of imitation "
                         "before PPO; e.g. distill_steps=4000000); without it nothing is distilled")
    if teacher is None and link != "perfect":
        raise ValueError(f"hyperparameter teacher_link={link!r} needs a teacher (hyperparameter "
                         "teacher=<controller>, with distill_steps > 0)")
    if teacher is None:
        return
    if _policy_kwargs(hp.get("policy_kwargs"))["recurrent"]:
        raise ValueError("hyperparameter teacher is not supported with policy_kwargs recurrent=True "
                         "(distillation trains a feedforward student)")
    if mode is not None and mode != "scratch":
        raise ValueError(f"hyperparameter teacher={teacher!r} needs mode='scratch' (got mode={mode!r}): a residual "
                         "agent already starts at its base")
    if env_id is not None and link == "perfect" and not env_id.endswith("-v1"):
        raise ValueError(f"hyperparameter teacher_link='perfect' needs a v1 env id (got {env_id!r}): the perfect "
                         "link substitutes v1 observation fields; use teacher_link='real'")


# --- the network ------------------------------------------------------------------------------

def _numpy_tanh_module():
    """``nn.Tanh`` with the forward computed by numpy's SIMD ``tanh`` (float32): torch 2.13's CPU
    ``tanh`` runs at about 2 ns per element here (550 us for a 4096 x 64 minibatch, a third of a
    PPO update) against 0.17 ns for numpy's; the values agree within a float32 ulp or two (a test
    checks them and the gradient against ``torch.tanh``). The backward is torch's own
    ``tanh_backward`` (g (1 - y^2) in one pass on the intra-op threads: 23 us for 4096 x 64 here,
    against 51 us for the three numpy passes it replaced)."""
    import torch
    from torch import nn

    class _Fn(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            y = torch.from_numpy(np.tanh(x.detach().contiguous().numpy()))
            ctx.save_for_backward(y)
            return y

        @staticmethod
        def backward(ctx, g):
            (y,) = ctx.saved_tensors
            return torch.ops.aten.tanh_backward(g, y)

    class NumpyTanh(nn.Module):
        def forward(self, x):
            if x.dtype != torch.float32:
                return torch.tanh(x)
            if torch.is_grad_enabled() and x.requires_grad:
                return _Fn.apply(x)
            return torch.from_numpy(np.tanh(x.detach().contiguous().numpy()))

    return NumpyTanh


def _build_net(obs_dim: int, pk: dict[str, Any]):
    import torch
    from torch import nn

    act = {"tanh": _numpy_tanh_module(), "relu": nn.ReLU}[pk["activation"]]

    def mlp(n_in: int, sizes: list[int], n_out: int, out_gain: float):
        layers, last = [], n_in
        for h in sizes:
            lin = nn.Linear(last, h)
            nn.init.orthogonal_(lin.weight, math.sqrt(2))
            nn.init.zeros_(lin.bias)
            layers += [lin, act()]
            last = h
        out = nn.Linear(last, n_out)
        nn.init.orthogonal_(out.weight, out_gain)
        nn.init.zeros_(out.bias)
        return nn.Sequential(*layers, out)

    class ActorCritic(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.recurrent = bool(pk["recurrent"])
            self.priv = PRIV_DIM if pk["privileged_critic"] else 0
            trunk = obs_dim
            if self.recurrent:
                self.gru = nn.GRUCell(obs_dim, pk["gru_size"])
                trunk = obs_dim + pk["gru_size"]
            self.actor = mlp(trunk, _arch(pk, "pi"), 3, 0.01)
            self.critic = mlp(trunk + self.priv, _arch(pk, "vf"), 1, 1.0)
            self.skip = nn.Linear(trunk, 3, bias=False) if pk["linear_skip"] else None
            if self.skip is not None:
                nn.init.zeros_(self.skip.weight)
            self.log_std = nn.Parameter(torch.full((3,), float(pk["log_std_init"])))
            self.squash = bool(pk["squash"])

        def initial_state(self, n: int):
            return torch.zeros(n, pk["gru_size"]) if self.recurrent else None

        def trunk(self, obs, h, first):
            """obs (N, D); h (N, H) or None; first (N,) bool: reset h there. Returns (features, h')."""
            if not self.recurrent:
                return obs, None
            h = h * (~first).float().unsqueeze(-1)
            h = self.gru(obs, h)
            return torch.cat([obs, h], dim=-1), h

        def mean(self, x):
            """The policy's mean action (before the env's clip): the actor, plus the linear skip
            term when the policy has one. Training and :meth:`BatchedAgent.predict` both call it."""
            return self.actor(x) if self.skip is None else self.actor(x) + self.skip(x)

        def heads(self, x, priv):
            mean = self.mean(x)
            cin = torch.cat([x, priv], dim=-1) if self.priv else x
            return mean, self.critic(cin).squeeze(-1)

    return ActorCritic()


class _RunningMeanStd:
    """Running mean and variance (Chan et al.'s parallel update, as SB3's RunningMeanStd).
    ``window`` > 0 caps the count at that many samples, so old samples fade out (a new batch of
    b samples then weighs b / (window + b)); 0 keeps every sample forever, as SB3.
    ``uncentered``: indices of the last axis whose mean is held at 0, so their "variance" is the
    running mean square (normalising divides them by their root mean square; zero stays zero)."""

    def __init__(self, shape: tuple[int, ...] = (), window: int = 0, uncentered: Sequence[int] = ()) -> None:
        self.mean = np.zeros(shape)
        self.var = np.ones(shape)
        self.count = 1e-4
        self.window = int(window)
        self.uncentered = np.asarray(sorted(set(int(i) for i in uncentered)), dtype=np.intp)

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64)
        b_mean, b_var, b_count = x.mean(axis=0), x.var(axis=0), x.shape[0]
        if self.uncentered.size:
            u = self.uncentered
            b_var[..., u] = np.mean(x[..., u] ** 2, axis=0)
            b_mean[..., u] = 0.0
        delta = b_mean - self.mean
        tot = self.count + b_count
        self.mean = self.mean + delta * b_count / tot
        m2 = self.var * self.count + b_var * b_count + delta ** 2 * self.count * b_count / tot
        self.var = m2 / tot
        self.count = min(tot, self.window) if self.window > 0 else tot


def _privileged(info: dict[str, Any], n: int) -> np.ndarray:
    """The true present reference relative to the follower (body frame dx, dy; cos, sin of the
    heading error), from the env's info (zeros if absent)."""
    ref, pose = info.get("true_reference"), info.get("follower_pose")
    if ref is None or pose is None:
        return np.zeros((n, PRIV_DIM), dtype=np.float32)
    bx, by = true_reference_body(info)
    de = ref[:, 2] - pose[:, 2]
    return np.stack([bx, by, np.cos(de), np.sin(de)], axis=-1).astype(np.float32)


# --- the trained agent as a policy -------------------------------------------------------------

class BatchedAgent:
    """A bppo agent as a policy over *raw* AUVFollow observations (SB3 ``predict`` protocol,
    one (W,) or a batch (N, W)): it owns its :class:`~agents.training.batched_obs.ObservationBuilder`
    (base controller, estimator, observer, history), the observation statistics and the
    network. Memory (builder, GRU state) restarts where ``episode_start`` is set and on the
    first call or a change of batch size.
    """

    env_wrapper = None  #: it reads raw observations: no wrapper

    def __init__(self, net: Any, stats: ObsStats | None, config: dict[str, Any], task_spec: Any,
                 name: str | None = None) -> None:
        from agents.training.batched_obs import ObservationBuilder

        self.net = net
        self.stats = stats
        self.config = config
        run = config["run"]
        self.env_id: str = run["env_id"]
        self.env_kwargs: dict = dict(run.get("env_kwargs") or {})
        self.mode: str = run["mode"]
        self.residual: dict | None = config.get("residual")
        self.builder_kwargs: dict = dict(config["observation"])
        self.task_spec = task_spec
        self.builder = ObservationBuilder(task_spec, **self.builder_kwargs)
        self.name = name or (f"BPPO+{self.residual['controller']} (residual)" if self.mode == "residual"
                             else "BPPO (scratch)")
        self._h = None
        self._n: int | None = None

    @property
    def recurrent(self) -> bool:
        return bool(getattr(self.net, "recurrent", False))

    def raw_policy(self, env_id: str | None = None, env_kwargs: dict | None = None) -> BatchedAgent:
        """This agent with its observation built for ``env_id`` (its base controller and
        estimator configured by that env's task spec)."""
        import gymnasium as gym

        env = gym.make(env_id or self.env_id, **(self.env_kwargs if env_kwargs is None else env_kwargs))
        spec = env.unwrapped.task_spec
        env.close()
        return BatchedAgent(self.net, self.stats, self.config, spec, name=self.name)

    def reset(self) -> None:
        self.builder.reset()
        self._n = None

    def normalize(self, feats: np.ndarray) -> np.ndarray:
        return feats if self.stats is None else self.stats.normalize(feats)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        import torch

        obs = np.asarray(observation)
        single = obs.ndim == 1
        if single:
            obs = obs[None, :]
        if obs.ndim != 2 or obs.shape[1] != self.builder.obs_width:
            raise ValueError(f"observation has shape {np.shape(observation)}: this agent reads raw AUVFollow "
                             f"observations ({self.builder.obs_width},) or (N, {self.builder.obs_width})")
        n = obs.shape[0]
        first = np.ones(n, dtype=bool) if self._n != n else (
            np.zeros(n, dtype=bool) if episode_start is None else np.asarray(episode_start, dtype=bool).reshape(n))
        if self._n != n:
            self.builder.reset()
            self._h = self.net.initial_state(n)
            self._n = n
        feats = self.normalize(self.builder.observe(obs, first))
        with torch.no_grad():
            x, self._h = self.net.trunk(torch.as_tensor(feats, dtype=torch.float32), self._h,
                                        torch.as_tensor(first))
            mean = self.net.mean(x)
            if not deterministic:
                mean = mean + torch.exp(self.net.log_std) * torch.randn_like(mean)
            if self.net.squash:
                mean = torch.tanh(mean)
        action = self.builder.act(mean.numpy().astype(np.float64))
        return (action[0] if single else action), state


def _load_model_file(path: Path) -> dict[str, Any]:
    from agents.training.torch_files import load_torch_file

    data = load_torch_file(path, "a bppo model file")
    if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{path} is not a bppo model: format={got!r}, expected {MODEL_FORMAT!r}")
    return data


def load_bppo_agent(model_path: Path, config: dict[str, Any], stats: ObsStats | None,
                    name: str | None = None) -> BatchedAgent:
    """The agent of a bppo run (called by :func:`agents.training.load_agent`)."""
    import gymnasium as gym

    data = _load_model_file(model_path)
    net = _build_net(int(data["obs_dim"]), _policy_kwargs(data["policy_kwargs"]))
    net.load_state_dict(data["state_dict"])
    net.eval()
    if stats is not None and stats.mean.shape != (int(data["obs_dim"]),):
        raise ValueError(f"the statistics beside {model_path} are for {stats.mean.shape} observations, the model "
                         f"observes ({data['obs_dim']},)")
    run = config["run"]
    env = gym.make(run["env_id"], **(run.get("env_kwargs") or {}))
    spec = env.unwrapped.task_spec
    env.close()
    return BatchedAgent(net, stats, config, spec, name=name)


# --- training ----------------------------------------------------------------------------------

def _save_model(path: Path, net: Any, opt: Any, obs_dim: int, pk: dict, steps: int, ret_rms: _RunningMeanStd) -> None:
    import torch

    data = {"format": MODEL_FORMAT, "state_dict": net.state_dict(), "optimizer": opt.state_dict(),
            "obs_dim": int(obs_dim), "policy_kwargs": dict(pk), "steps_done": int(steps),
            "ret_rms": {"mean": float(ret_rms.mean), "var": float(ret_rms.var), "count": float(ret_rms.count)}}
    tmp = path.with_name(path.name + ".tmp")
    try:
        torch.save(data, str(tmp))
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed write (disk full, read-only) leaves no partial file
        raise


def _stats(rms: _RunningMeanStd, clip_obs: float = CLIP_OBS, epsilon: float = EPS) -> ObsStats:
    return ObsStats(norm_obs=True, mean=rms.mean.copy(), var=rms.var.copy(), count=float(rms.count),
                    clip_obs=float(clip_obs), epsilon=float(epsilon), window=int(rms.window))


class _Diverged(Exception):
    """Training produced a non-finite action, loss or parameter (the message says which and when)."""


def _check_finite_parameters(net: Any, steps: int) -> None:
    import torch

    for name, p in net.named_parameters():
        if not bool(torch.isfinite(p).all()):
            raise _Diverged(f"the network's parameter {name} is not finite (NaN or inf) after the update at {steps:,} "
                            "steps")


def _phase_seconds(env: Any, phase: dict[str, float], elapsed: float) -> dict[str, float]:
    """Where the training loop's wall clock went (seconds): the vector env (physics and link), the
    agent's filter and observer, the residual's base controller, the policy's forward pass in the
    rollouts, the PPO update (GAE included), and the rest (normalisation, rewards, bookkeeping,
    evaluations, checkpoints)."""
    b = env.builder.timing
    parts = {"physics": env.physics_seconds, "filter_observer": b["observe"] - b["base"],
             "base_controller": b["base"], "policy_forward": phase["policy_forward"], "update": phase["update"]}
    parts["other"] = elapsed - sum(parts.values())
    return {k: round(float(v), 3) for k, v in parts.items()}


def _yaw_rate_penalty(raw: np.ndarray) -> np.ndarray:
    """r^2 per env [rad^2/s^2]: the follower's yaw rate (field ``r`` of the raw observation), squared."""
    from auv_follow_env.layout import OBS_INDEX

    return np.square(np.asarray(raw, dtype=np.float64)[:, OBS_INDEX["r"]])


def _heading_penalty(info: dict[str, Any], n: int) -> np.ndarray:
    """1 - cos(psi_ref - psi) per env (0 when the follower holds the reference heading, 2 when it
    faces the opposite way), from the env's true present reference and the follower's pose
    (zeros if the env gives neither)."""
    ref, pose = info.get("true_reference"), info.get("follower_pose")
    if ref is None or pose is None:
        return np.zeros(n)
    return 1.0 - np.cos(np.asarray(ref)[:, 2] - np.asarray(pose)[:, 2])


def _episode_errors(met: dict[str, Any]) -> list[float]:
    """Steady-state mean tracking errors [m] of the episodes that ended (the vector env's
    ``episode_metrics`` key ``steady_mean``: the true reference's error, eq. (65))."""
    return np.asarray(met.get("steady_mean", ()), dtype=float).reshape(-1).tolist()


def _finite_mean(x: list[float]) -> float:
    """The mean of the finite values of ``x``; NaN (without numpy's empty-slice warning) if none."""
    finite = [v for v in x if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _iqm(x: np.ndarray) -> float:
    """Interquartile mean; a missing value (NaN: e.g. an episode that ended before its steady
    state) counts as the worst (inf), so many of them make the IQM inf rather than hide."""
    x = np.sort(np.where(np.isnan(x), np.inf, np.asarray(x, dtype=np.float64)))
    k = len(x) // 4
    return float(x[k:len(x) - k].mean()) if len(x) >= 4 else float(x.mean())


def train_bppo(cfg: Any, plan: Any, resolved: dict[str, Any], run: Path, progress: Any, sigint: Any,
               write_yaml: Any) -> tuple[dict[str, Any], bool]:
    """The training loop of ``algo="bppo"`` (called by :func:`agents.training.train` after it
    validated everything and created the run directory). Returns (result dict, interrupted)."""
    import torch

    from agents.training.batched_env import BatchedTrainEnv
    from controllers.evaluation import evaluate_batched

    hp = {**BatchedPPO().__dict__, **{k: v for k, v in plan.hp.items() if k not in ("n_timesteps", "n_envs",
                                                                                      "normalize")}}
    pk = _policy_kwargs(hp.get("policy_kwargs"))
    torch.set_num_threads(int(hp["torch_threads"]))
    torch.manual_seed(cfg.seed)
    n_envs, T = plan.n_envs, int(hp["n_steps"])
    gamma, lam = float(hp["gamma"]), float(hp["gae_lambda"])
    norm = plan.norm_kw or {}
    norm_obs, norm_rew = bool(norm.get("norm_obs", True)) if plan.norm_kw else False, \
        bool(norm.get("norm_reward", True)) if plan.norm_kw else False
    # VecNormalize's settings, honoured as SB3 does (the defaults are SB3's: 10, 10, 1e-8, the algorithm's gamma)
    clip_obs, clip_rew = float(norm.get("clip_obs", CLIP_OBS)), float(norm.get("clip_reward", CLIP_REWARD))
    eps, rgamma = float(norm.get("epsilon", EPS)), float(norm.get("gamma", gamma))
    env = BatchedTrainEnv(cfg.env_id, n_envs, seed=cfg.seed, env_kwargs=cfg.env_kwargs,
                          builder=resolved["observation"], random_phase=bool(hp["random_phase"]), parallel=False)
    D = env.obs_dim
    net = _build_net(D, pk)
    opt = _adam(net, float(hp["learning_rate"]))
    lr0 = float(hp["learning_rate"])
    error_cols = env.builder.error_indices if hp["obs_error_norm"] == "scaled" else []
    obs_rms = _RunningMeanStd((D,), window=int(hp["obs_norm_window"]), uncentered=error_cols)
    ret_rms = _RunningMeanStd((), window=int(hp["reward_norm_window"]))
    # what this run applies, whatever the YAML said or left to the defaults
    resolved["training"] = {"lr_schedule": str(hp["lr_schedule"]), "learning_rate": float(hp["learning_rate"]),
                            "obs_norm_window": int(hp["obs_norm_window"]),
                            "obs_error_norm": str(hp["obs_error_norm"]), "obs_error_columns": list(error_cols),
                            "reward_norm_window": int(hp["reward_norm_window"]),
                            "norm_obs": norm_obs, "norm_reward": norm_rew,
                            "action_rate_coef": float(hp["action_rate_coef"]),
                            "heading_coef": float(hp["heading_coef"]),
                            "action_filter": float(hp["action_filter"]),
                            "bounds_loss_coef": float(hp["bounds_loss_coef"]),
                            "yaw_rate_coef": float(hp["yaw_rate_coef"]),
                            "yaw_from": hp.get("yaw_from")}
    start_steps = 0
    if cfg.resume_from is not None:
        data = _load_model_file(Path(cfg.resume_from))
        if int(data["obs_dim"]) != D or _policy_kwargs(data["policy_kwargs"]) != pk:  # checked before, by train
            env.close()
            raise ValueError(f"resume_from={cfg.resume_from!r} has another observation width or policy_kwargs")
        net.load_state_dict(data["state_dict"])
        opt.load_state_dict(data["optimizer"])
        for g in opt.param_groups:  # (a checkpoint of the looped Adam resumes on the fused kernel)
            g["lr"], g["fused"], g["foreach"] = float(hp["learning_rate"]), True, None
        start_steps = int(data["steps_done"])
        r = data["ret_rms"]
        ret_rms.mean, ret_rms.var, ret_rms.count = r["mean"], r["var"], r["count"]
        from agents.training.obs_stats import _stats_path

        sp = _stats_path(Path(cfg.resume_from), ".json")
        if norm_obs:  # train checked that the statistics exist and fit before it created the run
            st = read_obs_stats(sp)  # (and that its error fields were normalised as this run asks)
            obs_rms.mean, obs_rms.var, obs_rms.count = st.mean.copy(), st.var.copy(), st.count
    total = plan.total
    eval_seeds = list(range(cfg.eval_seed, cfg.eval_seed + max(int(hp["n_eval_seeds"]), 1)))
    resolved["eval_seeds"] = [eval_seeds[0], eval_seeds[-1]]
    writer = None
    if cfg.tensorboard:
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(run / "tb"))
        except ImportError:
            writer = None
    ckpt_dir = run / "checkpoints"
    eval_csv = run / "eval.csv"
    prog_csv = run / "progress.csv"
    eval_fields = ["steps", "train_seconds", "n_seeds", "true_steady_mean_m", "true_steady_iqm_m",
                   "true_full_mean_m", "return_mean", "terminated_frac"]
    prog_fields = ["steps", "train_seconds", "steps_per_s", "ep_return_mean", "ep_true_steady_mean_m", "episodes",
                   "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "std_mean", "learning_rate",
                   "dF_u_mean_N"]
    if not eval_csv.exists():
        with open(eval_csv, "w", newline="") as f:
            csv.writer(f).writerow(eval_fields)
    if not prog_csv.exists():
        with open(prog_csv, "w", newline="") as f:
            csv.writer(f).writerow(prog_fields)

    def normalize(x: np.ndarray, update: bool) -> np.ndarray:
        if not norm_obs:
            return x.astype(np.float32)
        if update:
            obs_rms.update(x)
        return np.clip((x - obs_rms.mean) / np.sqrt(obs_rms.var + eps), -clip_obs, clip_obs).astype(np.float32)

    def evaluate_now(steps: int, seconds: float) -> dict[str, float]:
        agent = BatchedAgent(net, _stats(obs_rms, clip_obs, eps) if norm_obs else None, resolved, env.spec)
        net.eval()
        df = evaluate_batched([agent], cfg.env_id, eval_seeds, env_kwargs=cfg.env_kwargs, progress=False)
        net.train()
        row = {"steps": steps, "train_seconds": round(seconds, 2), "n_seeds": len(eval_seeds),
               "true_steady_mean_m": float(df["true_steady_mean"].mean()),
               "true_steady_iqm_m": _iqm(df["true_steady_mean"].to_numpy()),
               "true_full_mean_m": float(df["true_full_mean"].mean()), "return_mean": float(df["return"].mean()),
               "terminated_frac": float(df["terminated"].mean())}
        with open(eval_csv, "a", newline="") as f:
            csv.writer(f).writerow([row[k] for k in eval_fields])
        if writer is not None:
            for k in ("true_steady_mean_m", "true_steady_iqm_m", "return_mean"):
                writer.add_scalar(f"eval/{k}", row[k], steps)
        return row

    def save(path: Path, stats_path: Path, steps: int) -> None:
        _save_model(path, net, opt, D, pk, steps, ret_rms)
        if norm_obs:
            write_obs_stats(_stats(obs_rms, clip_obs, eps), stats_path)

    def status(steps: int, seconds: float) -> None:
        resolved["steps_done"] = int(steps)
        resolved["train_seconds"] = round(float(seconds), 2)
        write_yaml(run / "config.yaml", resolved)

    rate_coef, heading_coef = float(hp["action_rate_coef"]), float(hp["heading_coef"])
    yaw_coef = float(hp["yaw_rate_coef"])
    prev_exec = np.zeros((n_envs, 3))  # the env action of each env's previous step (in [-1, 1])
    limits = np.asarray(env.spec.force_limits, dtype=np.float64)
    teacher, distill_steps = _make_teacher(hp, env), int(hp["distill_steps"])
    mix_rng = np.random.default_rng([cfg.seed, 0xD15])
    raw_obs = env.reset()
    priv = _privileged(env.info, n_envs) if net.priv else None
    first = np.ones(n_envs, dtype=bool)
    h = net.initial_state(n_envs)
    ret_acc = np.zeros(n_envs)
    steps = start_steps
    t0 = time.perf_counter()
    progress.t0 = t0  # the time budget's clock (--max-minutes) starts with the loop
    ckpt_freq, eval_freq = int(cfg.checkpoint_freq or 0), int(cfg.eval_freq or 0)
    next_ckpt = (steps // ckpt_freq + 1) * ckpt_freq if ckpt_freq else math.inf
    next_eval = (steps // eval_freq + 1) * eval_freq if eval_freq else math.inf
    max_s = 60.0 * cfg.max_minutes if cfg.max_minutes is not None else math.inf
    interrupted, last_eval = False, None
    log_std_min = LOG_STD_MIN
    squash = net.squash
    diverged: str | None = None
    ep_returns: list[float] = []
    ep_errors: list[float] = []
    df_sum, df_n = np.zeros(3), 0  # |dF| per step [N, N, N m] over the valid transitions of an update
    phase = {"policy_forward": 0.0, "update": 0.0}  # wall-clock seconds of the trainer's own phases
    if eval_freq and start_steps == 0:
        last_eval = evaluate_now(0, 0.0)
    try:
        while steps < total:
            if sigint.requested or time.perf_counter() - t0 >= max_s:
                interrupted = sigint.requested
                break
            buf_obs = np.zeros((T, n_envs, D), dtype=np.float32)
            buf_priv = np.zeros((T, n_envs, PRIV_DIM), dtype=np.float32) if net.priv else None
            buf_first = np.zeros((T, n_envs), dtype=bool)
            buf_act = np.zeros((T, n_envs, 3), dtype=np.float32)
            buf_logp = np.zeros((T, n_envs), dtype=np.float32)
            buf_val = np.zeros((T + 1, n_envs), dtype=np.float32)
            buf_rew = np.zeros((T, n_envs), dtype=np.float32)
            buf_term = np.zeros((T, n_envs), dtype=bool)
            buf_done = np.zeros((T, n_envs), dtype=bool)
            buf_valid = np.zeros((T, n_envs), dtype=bool)
            h0 = h.clone() if h is not None else None
            distilling = teacher is not None and steps < distill_steps
            buf_teach = np.zeros((T, n_envs, 3), dtype=np.float32) if distilling else None
            with torch.no_grad():
                for t in range(T):
                    o = normalize(raw_obs, update=True)
                    buf_obs[t], buf_first[t] = o, first
                    tp = time.perf_counter()
                    ot = torch.from_numpy(o)
                    x, h = net.trunk(ot, h, torch.from_numpy(first))
                    pv = None
                    if net.priv:
                        buf_priv[t] = priv
                        pv = torch.from_numpy(priv)
                    mean, value = net.heads(x, pv)
                    std = torch.exp(net.log_std.clamp(min=log_std_min))
                    a = mean + std * torch.randn_like(mean)
                    logp = (-0.5 * ((a - mean) / std) ** 2 - torch.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)
                    buf_act[t], buf_logp[t], buf_val[t] = a.numpy(), logp.numpy(), value.numpy()
                    phase["policy_forward"] += time.perf_counter() - tp
                    if not np.isfinite(buf_act[t]).all():
                        raise _Diverged(f"the policy's actions are not finite (NaN or inf) at {steps:,} steps")
                    act = a.numpy().astype(np.float64)
                    if squash:  # the env gets tanh(a); the buffer keeps a (the ratio's Jacobians cancel)
                        act = np.tanh(act)
                    if distilling:  # DAgger: label with the teacher, act with a mix that ends at the student
                        student = (torch.tanh(mean) if squash else mean).numpy()
                        act, buf_teach[t] = _teacher_step(teacher, env, first, student, steps, distill_steps, mix_rng)
                    raw_obs, rew, term, trunc, info = env.step(act)
                    valid = ~info["prev_done"]
                    # the change of the executed action (none at an episode's first step)
                    change = np.where(first[:, None], 0.0, env.last_action - prev_exec)
                    prev_exec = env.last_action.copy()
                    if valid.any():
                        df_sum += np.abs(change[valid] * limits).sum(axis=0)
                        df_n += int(valid.sum())
                    if rate_coef > 0.0:  # the action-rate term: -c ||a_k - a_{k-1}||^2 (action units)
                        rew = rew - rate_coef * np.sum(change * change, axis=1)
                    if heading_coef > 0.0:  # the heading term: -c (1 - cos(psi_ref - psi)), true present psi_ref
                        rew = rew - heading_coef * _heading_penalty(info, n_envs)
                    if yaw_coef > 0.0:  # the yaw-rate term: -c r^2, the follower's own measured yaw rate [rad/s]
                        rew = rew - yaw_coef * _yaw_rate_penalty(env.raw)
                    done = term | trunc
                    if norm_rew:
                        ret_acc = ret_acc * rgamma + rew
                        ret_rms.update(ret_acc[valid] if valid.any() else ret_acc)
                        ret_acc[done] = 0.0
                        r = np.clip(rew / np.sqrt(ret_rms.var + eps), -clip_rew, clip_rew)
                    else:
                        r = rew
                    buf_rew[t], buf_term[t], buf_done[t], buf_valid[t] = r, term, done, valid
                    first = info["prev_done"].copy()
                    if net.priv:
                        priv = _privileged(info, n_envs)
                    if "episodes" in info:
                        rets, _, met = info["episodes"]
                        ep_returns.extend(rets.tolist())
                        ep_errors.extend(_episode_errors(met))
                o = normalize(raw_obs, update=False)
                x, _ = net.trunk(torch.from_numpy(o), h, torch.from_numpy(first))
                _, last_v = net.heads(x, torch.from_numpy(priv) if net.priv else None)
                buf_val[T] = last_v.numpy()
            steps += T * n_envs
            tu = time.perf_counter()
            # GAE; a transition out of an episode's last observation (not valid) is a dummy
            adv = np.zeros((T, n_envs), dtype=np.float32)
            last = np.zeros(n_envs, dtype=np.float32)
            for t in reversed(range(T)):
                delta = buf_rew[t] + gamma * buf_val[t + 1] * (~buf_term[t]) - buf_val[t]
                last = delta + gamma * lam * (~buf_done[t]) * last
                last = np.where(buf_valid[t], last, 0.0).astype(np.float32)
                adv[t] = last
            ret = adv + buf_val[:T]
            if hp["lr_schedule"] == "linear":  # linear decay to 0 at total steps (CleanRL's anneal_lr)
                for g in opt.param_groups:
                    g["lr"] = lr0 * max(1.0 - (steps - T * n_envs) / total, 0.0)
            if distilling:
                stats = _distill_update(net, opt, hp, buf_obs, buf_priv, buf_teach, ret, buf_valid)
            else:
                stats = _update(net, opt, hp, buf_obs, buf_priv, buf_first, buf_act, buf_logp, adv, ret, buf_valid,
                                h0, log_std_min)
            _check_finite_parameters(net, steps)
            phase["update"] += time.perf_counter() - tu
            elapsed = time.perf_counter() - t0
            progress.update(steps)
            row = {"steps": steps, "train_seconds": round(elapsed, 2),
                   "steps_per_s": round((steps - start_steps) / max(elapsed, 1e-9), 1),
                   "ep_return_mean": float(np.mean(ep_returns)) if ep_returns else float("nan"),
                   # (episodes that ended before the steady state have no steady error: left out)
                   "ep_true_steady_mean_m": _finite_mean(ep_errors),
                   "episodes": len(ep_returns), **stats, "learning_rate": opt.param_groups[0]["lr"],
                   "dF_u_mean_N": float(df_sum[0] / max(df_n, 1))}
            ep_returns.clear()
            ep_errors.clear()
            df_sum, df_n = np.zeros(3), 0
            with open(prog_csv, "a", newline="") as f:
                csv.writer(f).writerow([row[k] for k in prog_fields])
            if writer is not None:
                for k in prog_fields[2:]:
                    if np.isfinite(row[k]):
                        writer.add_scalar(f"train/{k}", row[k], steps)
            if steps >= next_ckpt:
                ckpt_dir.mkdir(exist_ok=True)
                save(ckpt_dir / f"model_{steps}_steps.zip", ckpt_dir / f"model_vecnormalize_{steps}_steps.json", steps)
                next_ckpt = (steps // ckpt_freq + 1) * ckpt_freq
                status(steps, elapsed)
            if steps >= next_eval:
                last_eval = evaluate_now(steps, elapsed)
                next_eval = (steps // eval_freq + 1) * eval_freq
                status(steps, elapsed)
    except KeyboardInterrupt:
        interrupted = True
    except _Diverged as exc:
        diverged = str(exc)
    finally:
        progress.close()
        elapsed = time.perf_counter() - t0
        env.close()
        if writer is not None:
            writer.close()
    # saved after a finished run or Ctrl-C; a diverged network is not saved (the checkpoints before it are kept)
    status(steps, elapsed)
    if diverged is None:
        save(run / "model.zip", run / "vecnormalize.json", steps)
    result = {"num_timesteps": steps, "start_timesteps": start_steps, "wall_clock_s": round(elapsed, 2),
              "steps_per_s": round((steps - start_steps) / max(elapsed, 1e-9), 1), "interrupted": interrupted,
              "phase_seconds": _phase_seconds(env, phase, elapsed)}
    if diverged is not None:
        result["failed"] = f"training diverged: {diverged}"
        return result, interrupted
    if cfg.final_eval and not interrupted:
        row = evaluate_now(steps, elapsed) if (last_eval is None or last_eval["steps"] != steps) else last_eval
        result["final_score"] = {"seeds": [eval_seeds[0], eval_seeds[-1]],
                                 "true_steady_mean_m": row["true_steady_mean_m"],
                                 "true_steady_iqm_m": row["true_steady_iqm_m"],
                                 "true_full_mean_m": row["true_full_mean_m"], "return": row["return_mean"]}
        print(f"final score on {cfg.env_id}, {len(eval_seeds)} seeds {eval_seeds[0]}-{eval_seeds[-1]}: steady-state "
              f"mean error to the true reference {row['true_steady_mean_m']:.4f} m (IQM "
              f"{row['true_steady_iqm_m']:.4f} m), mean return {row['return_mean']:.1f}", file=sys.stderr)
    return result, interrupted


class _Teacher:
    """A scripted controller labelling the student's states (module docstring, "Distillation")."""

    def __init__(self, name: str, spec: Any, link: str) -> None:
        from controllers import make_controller

        self.controller = make_controller(name, spec)
        self.link, self.spec = link, spec
        self.limits = np.asarray(spec.force_limits, dtype=np.float64)
        self.dob = getattr(self.controller, "disturbance_observer", None)

    def label(self, raw: np.ndarray, info: dict[str, Any], start: np.ndarray) -> np.ndarray:
        """The teacher's action (N, 3) in [-1, 1] for the env's present raw observations."""
        seen = np.asarray(raw, dtype=np.float64)
        if self.link == "perfect":
            from auv_follow_env.perfect_link import perfect_link_observation

            seen = perfect_link_observation(seen, info["true_target"], info["follower_pose"], self.spec.p_d)
        action, _ = self.controller.predict(np.asarray(seen, dtype=np.float64), episode_start=start)
        return np.asarray(action, dtype=np.float64)

    def applied(self, action: np.ndarray) -> None:
        """Tell the teacher's disturbance observer the force the env was commanded (it was not
        necessarily the teacher's own)."""
        if self.dob is not None:
            self.dob.applied(np.clip(action, -1.0, 1.0) * self.limits)


def _make_teacher(hp: dict[str, Any], env: Any) -> _Teacher | None:
    if hp.get("teacher") is None or int(hp.get("distill_steps", 0)) == 0:
        return None
    return _Teacher(hp["teacher"], env.spec, hp.get("teacher_link", "perfect"))


def mix_probability(steps: int, distill_steps: int) -> float:
    """The probability that an env executes the teacher's action (not the student's) at a
    rollout starting after ``steps`` env steps: 1 at the start, falling linearly to 0 at half of
    ``distill_steps``, then 0 (DAgger's beta schedule: the student then acts alone and is
    labelled on the states it reaches itself)."""
    half = 0.5 * max(int(distill_steps), 1)
    return float(min(max(1.0 - steps / half, 0.0), 1.0))


def _teacher_step(teacher: _Teacher, env: Any, first: np.ndarray, student: np.ndarray, steps: int,
                  distill_steps: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(executed action (N, 3) float64, teacher label (N, 3) float32) for one distillation step.
    The student acts with its mean (no exploration noise)."""
    label = teacher.label(env.raw, env.info, first)
    use = rng.random(label.shape[0]) < mix_probability(steps, distill_steps)
    act = np.where(use[:, None], label, np.clip(np.asarray(student, dtype=np.float64), -1.0, 1.0))
    teacher.applied(act)
    return act, label.astype(np.float32)


def _distill_update(net: Any, opt: Any, hp: dict, obs, priv, teach, ret, valid) -> dict[str, float]:
    """Epochs of regression over the rollout: the actor's mean onto the teacher's action (mean
    squared error, reported as ``policy_loss``) plus ``vf_coef`` x the critic's error on the
    rollout's returns (so PPO starts with a critic of the student's behaviour)."""
    import torch

    T, N = valid.shape
    vf_coef, max_norm, batch = float(hp["vf_coef"]), float(hp["max_grad_norm"]), int(hp["batch_size"])
    o_t, y_t, ret_t = torch.from_numpy(obs), torch.from_numpy(teach), torch.from_numpy(ret)
    p_t = torch.from_numpy(priv) if priv is not None else None
    idx_all = torch.nonzero(torch.from_numpy(valid).reshape(-1)).squeeze(-1)
    logs: dict[str, list[float]] = {"policy_loss": [], "value_loss": []}
    for _ in range(int(hp["n_epochs"])):
        idx = idx_all[torch.randperm(idx_all.numel())]
        for g in (idx[i:i + batch] for i in range(0, idx.numel(), batch)):
            t_i, n_i = g // N, g % N
            x, _ = net.trunk(o_t[t_i, n_i], None, None)
            mean, value = net.heads(x, p_t[t_i, n_i] if p_t is not None else None)
            if net.squash:
                mean = torch.tanh(mean)
            bc = ((mean - y_t[t_i, n_i]) ** 2).sum(-1).mean()
            vl = 0.5 * ((value - ret_t[t_i, n_i]) ** 2).mean()
            loss = bc + vf_coef * vl
            if not bool(torch.isfinite(loss)):
                raise _Diverged(f"the imitation loss is not finite ({loss.item()!r}: policy {bc.item()!r}, value "
                                f"{vl.item()!r})")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), max_norm, foreach=True)
            opt.step()
            logs["policy_loss"].append(bc.item())
            logs["value_loss"].append(vl.item())
    out = {k: float(np.mean(v)) if v else float("nan") for k, v in logs.items()}
    out.update(entropy=float("nan"), approx_kl=float("nan"), clip_frac=float("nan"),
               std_mean=float(torch.exp(net.log_std).mean().item()))
    return out


def _adam(net: Any, lr: float) -> Any:
    """Adam as SB3 configures it for PPO (eps 1e-5), with torch's fused CPU kernel: one pass over
    all parameters instead of a Python loop over the parameter tensors (under torch's profiler
    1.2 ms against 0.4 ms per 4096-sample minibatch step; 3-11 % of a whole update). Same update
    rule; the last bits may differ from the looped form."""
    import torch

    return torch.optim.Adam(net.parameters(), lr=lr, eps=1e-5, fused=True)


def _update(net: Any, opt: Any, hp: dict, obs, priv, first, act, logp_old, adv, ret, valid, h0,
            log_std_min: float) -> dict[str, float]:
    """PPO epochs over the rollout: minibatches of samples (feedforward) or of whole env
    sequences (recurrent)."""
    import torch

    T, N = valid.shape
    clip, ent_coef, vf_coef = float(hp["clip_range"]), float(hp["ent_coef"]), float(hp["vf_coef"])
    bounds_coef = float(hp.get("bounds_loss_coef", 0.0))
    max_norm, target_kl = float(hp["max_grad_norm"]), hp.get("target_kl")
    o_t, a_t = torch.from_numpy(obs), torch.from_numpy(act)
    lp_t, adv_t, ret_t = torch.from_numpy(logp_old), torch.from_numpy(adv), torch.from_numpy(ret)
    v_t, f_t = torch.from_numpy(valid), torch.from_numpy(first)
    p_t = torch.from_numpy(priv) if priv is not None else None
    batch = int(hp["batch_size"])
    logs = {"policy_loss": [], "value_loss": [], "entropy": [], "approx_kl": [], "clip_frac": []}
    stop = False
    for _ in range(int(hp["n_epochs"])):
        if net.recurrent:
            envs_per_mb = max(1, batch // T)
            perm = torch.randperm(N)
            groups = [perm[i:i + envs_per_mb] for i in range(0, N, envs_per_mb)]
        else:  # one gather per epoch of the shuffled valid samples; the minibatches are slices of it
            idx = torch.nonzero(v_t.reshape(-1)).squeeze(-1)
            idx = idx[torch.randperm(idx.numel())]
            shuffled = [None if z is None else z.reshape(T * N, *z.shape[2:]).index_select(0, idx)
                        for z in (o_t, a_t, lp_t, adv_t, ret_t, p_t)]
            groups = [slice(i, i + batch) for i in range(0, idx.numel(), batch)]
        for g in groups:
            if net.recurrent:
                h = h0[g]
                xs = []
                for t in range(T):
                    x, h = net.trunk(o_t[t, g], h, f_t[t, g])
                    xs.append(x)
                x = torch.stack(xs)  # (T, n, F)
                m = v_t[:, g]
                x, a, lp, ad, rt = x[m], a_t[:, g][m], lp_t[:, g][m], adv_t[:, g][m], ret_t[:, g][m]
                pv = p_t[:, g][m] if p_t is not None else None
            else:
                o, a, lp, ad, rt, pv = (None if z is None else z[g] for z in shuffled)
                x, _ = net.trunk(o, None, None)
            if ad.numel() < 2:
                continue
            mean, value = net.heads(x, pv)
            log_std = net.log_std.clamp(min=log_std_min)
            std = torch.exp(log_std)
            lp_new = (-0.5 * ((a - mean) / std) ** 2 - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
            ratio = torch.exp(lp_new - lp)
            ad = (ad - ad.mean()) / (ad.std() + 1e-8)
            pg = torch.max(-ad * ratio, -ad * ratio.clamp(1 - clip, 1 + clip)).mean()
            vl = 0.5 * ((value - rt) ** 2).mean()
            ent = (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum()
            loss = pg + vf_coef * vl - ent_coef * ent
            if bounds_coef > 0.0:  # the mean pulled back inside the env's action box [-1, 1]
                loss = loss + bounds_coef * (torch.relu(mean.abs() - 1.0) ** 2).sum(-1).mean()
            if not bool(torch.isfinite(loss)):
                raise _Diverged(f"the PPO loss is not finite ({loss.item()!r}: policy {pg.item()!r}, value "
                                f"{vl.item()!r}, entropy {ent.item()!r})")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), max_norm, foreach=True)
            opt.step()
            with torch.no_grad():
                kl = ((ratio - 1) - torch.log(ratio)).mean().item()
                logs["approx_kl"].append(kl)
                logs["clip_frac"].append(((ratio - 1).abs() > clip).float().mean().item())
            logs["policy_loss"].append(pg.item())
            logs["value_loss"].append(vl.item())
            logs["entropy"].append(ent.item())
            if target_kl is not None and kl > 1.5 * float(target_kl):
                stop = True
                break
        if stop:
            break
    out = {k: float(np.mean(v)) if v else float("nan") for k, v in logs.items()}
    out["std_mean"] = float(torch.exp(net.log_std).mean().item())
    return out
