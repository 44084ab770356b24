"""AUVFollowEnv: the single Gymnasium environment (a batch-of-one shell over BatchSim)."""

from __future__ import annotations

from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from auv_follow_env import dynamics as dyn
from auv_follow_env.link_trace import TraceLink, read_link_trace
from auv_follow_env.metrics import tracking_metrics
from auv_follow_env.params import TaskSpec
from auv_follow_env.sim import BatchSim, check_sincos
from auv_follow_env.tiers import make_env_config, tier_table_markdown

__all__ = ["AUVFollowEnv", "check_action"]

_IDX0 = np.zeros(1, dtype=np.int64)
_FAST_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
_SHAPE3 = (3,)


def check_action(action: Any, shape: tuple[int, ...]) -> np.ndarray:
    """Return ``action`` as a numeric ndarray of ``shape`` or raise a clear error.

    Finiteness is checked by the kernel before anything changes.
    """
    if isinstance(action, np.ndarray):
        a = action
    else:
        try:
            a = np.asarray(action)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"action={action!r} is not a numeric array: {exc}") from exc
    if a.dtype.kind not in "fiu" or a.dtype.kind == "b":
        raise ValueError(f"action has dtype {a.dtype}: a real-valued array of shape {shape} in "
                         f"[-1, 1] is expected")
    if a.shape != shape:
        raise ValueError(f"action has shape {a.shape}: expected {shape} (F_u, F_v, F_r in [-1, 1])")
    return np.ascontiguousarray(a, dtype=np.float64)


class AUVFollowEnv(gym.Env[np.ndarray, np.ndarray]):
    r"""Delayed dynamic target following by an underwater robot (Zhang et al. 2026).

    ## Description

    A planar 3-DOF underwater robot (eqs. (1)-(9)) must hold a reference point
    ``p_d = [-0.65, 0.12] m`` behind a manoeuvring target (eq. (21)), while the target's
    pose and velocity reach it only ``tau`` seconds late (eq. (12)), under an ocean current,
    lumped disturbances and damping mismatch. The paper's controllers are in
    ``controllers``; this env is the plant and the task.

    ## Action Space

    ``Box(-1, 1, (3,), float32)``, scaled by ``force_limits`` and held over the control
    step. Values outside [-1, 1] are clipped; NaN/inf, wrong shape or non-numeric dtype
    raise ``ValueError`` and leave the env untouched.

    | Num | Action | Physical at +-1 (default) |
    |-----|--------|---------------------------|
    | 0   | surge force F_u | +-150 N |
    | 1   | sway force F_v  | +-150 N |
    | 2   | yaw moment F_r  | +-30 N m |

    ## Observation Space

    ``Box(-inf, inf, (16,), float32)``, all in the follower's body frame, SI units; layout
    in :mod:`auv_follow_env.layout` (decode by name with ``layout.decode``):

    | Num | Name | Unit | Meaning |
    |-----|------|------|---------|
    | 0-2 | u, v, r | m/s, m/s, rad/s | follower body velocity (ground-referenced) |
    | 3-4 | cos_psi, sin_psi | - | follower heading (compass) |
    | 5-6 | target_dx, target_dy | m | delayed target position relative to the follower |
    | 7-8 | target_cos_dpsi, target_sin_dpsi | - | delayed target heading relative to the follower |
    | 9-11 | target_u, target_v, target_r | m/s, m/s, rad/s | delayed target body velocity |
    | 12-13 | ref_dx, ref_dy | m | delayed reference point (no prediction) relative to follower |
    | 14-15 | current_u, current_v | m/s | measured current in the body frame (eq. (5)) |

    The true present target is never observed. Before ``t = tau`` the follower receives the
    target's genuine state at ``t - tau < 0``: the target is simulated from ``t = -tau``.
    The static facts a controller may use (tau, p_d, psi_d, nominal model, dt, force limits)
    are in the immutable :class:`~auv_follow_env.params.TaskSpec` ``env.unwrapped.task_spec``.

    ## Rewards

    ``r = -||p - p_ref_true|| - effort_weight * mean(a^2)`` with ``p_ref_true`` from eq. (21)
    with the *present* target (psi_d = 0). ``effort_weight`` is 0 by default. On termination
    the reward also carries ``-max_distance_m`` for each remaining step, so ending early never
    pays.

    ## Starting State

    The target starts at the origin heading +x at ``t = -tau`` with random manoeuvre phases.
    The follower starts at rest with the delayed target's heading, ``init_offset_m`` (0.87 m)
    behind the delayed reference point. Current periods/phases and disturbance phases are
    drawn from the env's generator (``reset(seed=...)``).

    ## Episode End

    Truncation after ``episode_s`` (60 s = 1200 steps by default), done by the env itself:
    the ids register no ``max_episode_steps``, so changing ``episode_s`` or ``dt`` through
    ``gym.make`` just works. (A ``max_episode_steps`` passed to ``gym.make`` adds Gymnasium's
    TimeLimit on top; one shorter than the episode ends it without ``episode_metrics``.)
    Termination when the follower is more than ``max_distance_m`` (20 m) from the true
    reference, or the state is not finite.

    ## Info

    Every step: ``tracking_error`` (m, to the true reference), ``time`` (s), and for
    evaluation only - never for policies - ``true_target`` (x, y, psi, u, v, r),
    ``true_reference`` (x, y, psi) and ``follower_pose`` (x, y, psi). At the episode's end:
    ``episode_metrics`` with the paper's mean / RMSE / max over the full run and t >= 10 s
    (eqs. (64)-(65)), against the true reference. Samples are the states after each step.

    ## Scenarios (Table 2) and disturbance levels (Table 3)

    | Id | v_t (m/s) | tau (s) | level | damping mismatch | manoeuvres a_u, P_u; a_r, P_r |
    |----|-----------|---------|-------|------------------|-------------------------------|
    | S1 | 0.45 | 0.5 | L0 | +15 % | 0.025, 30 s; 0.02 rad/s, 40 s |
    | S2 | 0.49 | 1.0 | L1 | +60 % | 0.075, 20 s; 0.05 rad/s, 30 s |
    | S3 | 0.49 | 1.5 | L2 | +60 % | 0.075, 20 s; 0.05 rad/s, 30 s |
    | S4 | 0.52 | 2.0 | L2 | +105 % | 0.10, 15 s; 0.07 rad/s, 24 s |

    | Level | current x (m/s) | current y (m/s) | peaks (d_u, d_v, d_r) per unit mass |
    |-------|-----------------|-----------------|-------------------------------------|
    | L0 | 0 | 0 | 0 |
    | L1 | [0.01, 0.03] | [-0.018, 0.002] | (0.02, 0.015, 0.008) |
    | L2 | [0.02, 0.10] | [-0.065, 0.01] | (0.08, 0.065, 0.028) |

    ## Arguments

    ``gym.make("AUVFollow-S4-v0", disturbance="L1", delay_s=1.0)`` or
    ``gym.make("AUVFollow-v0", scenario="S2")``. Overrides: ``delay_s``, ``episode_s``,
    ``dt`` (0.05 s), ``physics_substeps`` (2), ``mismatch``, ``force_limits``,
    ``init_offset_m``, ``max_distance_m``, ``effort_weight``, ``p_d``, ``psi_d``,
    ``steady_start_s``; see :class:`~auv_follow_env.params.EnvConfig`.

    ``sincos`` (on every id): how each step's sin/cos are computed (the ten tones, both headings
    at every substep and the observation's relative heading: all 15 sin/cos pairs of a v0 step;
    v1's random draws, the reset's warm-up and the rare heading increments beyond 0.25 rad keep
    libm either way). ``"simd"`` (the default since 0.2.0): a branch-free polynomial
    (:func:`~auv_follow_env.dynamics.fast_sincos`, within 1 ULP) in SIMD loops, several times
    faster than glibc's scalar calls (results/bench_vector.md). ``"libm"``: glibc's sin/cos, the
    path the v0 golden arrays (tests/data/frozen_v0.npz) were recorded with and the default in
    0.1.0. The two differ in the last bit of about 3 % of the values, so trajectories differ
    by rounding-level amounts (over the v0 golden set at most 1.8e-15 m in the follower's pose,
    observations identical; tests/test_fast_math.py and tests/test_frozen_v0.py bound them). The
    frozen v0 contract is a tolerance (1e-9 relative), not bit identity, which never held across
    hosts anyway; determinism within one host is exact either way. ``fast_math`` is the former
    name (``True`` = ``"simd"``, ``False`` = ``"libm"``).

    ## v1: the acoustic link (``AUVFollow-Easy-v1`` ... ``-Extreme-v1``, ``AUVFollow-v1``)

    The same plant, action, reward and episode end; what changes is what the follower hears
    and how the target moves (all in the one kernel, per env, from the env's own generator):

    * **Packets.** The target's state is measured at send times (period ``update_period_s``,
      each interval +- ``period_jitter_s``, on the control grid) and arrives after its own
      latency: ``latency_model`` "constant" (``latency_s``), "uniform" (``latency_s`` +-
      ``latency_spread_s``) or "gauss_markov" (mean ``latency_s``, std ``latency_spread_s``,
      correlation time ``latency_corr_s``; clipped at 0). Packets are lost i.i.d. with
      ``loss_prob`` and in bursts (Gilbert-Elliott: good -> bad with ``burst_p_good_bad`` per
      packet, bad -> good with ``burst_p_bad_good``, loss ``burst_loss_bad`` while bad). A packet
      arriving after a newer one is discarded, so the observation never goes back in time.
    * **Fix noise.** Gaussian position noise with sigma ``fix_sigma_m + fix_sigma_per_m * range``
      (as a USBL's), heading, velocity and yaw-rate noise.
    * **Target.** u_t = clip(v_bar (1 + a_u sin) + X_u, min, max), r_t = clip(a_r sin + X_r,
      +-max), with X_u, X_r Ornstein-Uhlenbeck processes (std ``target_speed_std`` /
      ``target_yaw_rate_std``, correlation times ``target_*_corr_s``), sampled exactly at the
      control rate and held over each step. The tiers set the tones to 0: no period to lock on.
    * **Current and disturbances.** A Gauss-Markov current (mean speed ``current_speed``, std
      ``current_speed_std``, correlation ``current_corr_s``, direction random walk
      ``current_direction_drift``) on top of the level's tones (``current_x`` / ``current_y``
      replace the level's ranges: a custom current); coloured disturbances
      ``disturbance_noise_*`` (per unit mass, correlation ``disturbance_corr_s``).
    * **Thrusters.** First-order lag ``thruster_tc_s`` and rate limit ``thruster_rate``
      (fraction of the force limit per second) between the action and the applied force.
    * **Start.** The target and the link run for ``warmup_s`` before t = 0; the follower starts
      behind the newest packet received by then (behind the true target if none).

    Observation: ``Box(-inf, inf, (20,), float32)``, fields 0-15 as above with "delayed target"
    meaning the newest received packet, then

    | Num | Name | Unit | Meaning |
    |-----|------|------|---------|
    | 16 | packet_age | s | now minus the packet's measurement time |
    | 17 | since_arrival | s | now minus the packet's arrival time |
    | 18 | new_packet | - | 1 on the step a newer packet arrived |
    | 19 | has_packet | - | 0 until the first packet (fields 5-13, 16-17 are 0 then) |

    Info: at reset ``condition`` (the drawn settings of this episode, a dict); at the end
    ``link_stats`` (packets sent, lost, arrived, discarded, overflow since t = 0). Every v1
    field is a ``gym.make`` keyword: a number fixes it, a ``(min, max)`` pair draws it per reset.
    ``link_trace`` (a ``.csv``/``.parquet`` file or a DataFrame; :mod:`auv_follow_env.link_trace`, docs/data.md)
    replays a recorded link in place of the link model: the follower hears the trace's packets,
    while the plant, target and current run as without it (``info["link_trace"]`` at reset names it).
    v0's constant delay is the setting ``update_period_s = dt``, ``latency_s = tau``,
    ``warmup_s = tau``, no loss, no noise, no processes (``AUVFollow-v1`` with those keywords
    reproduces ``AUVFollow-v0``'s plant trajectory).

    ## Rendering

    ``render_mode`` (a ``gym.make`` keyword): ``None`` (default, nothing drawn), ``"rgb_array"``
    (``env.render()`` returns the present frame, a ``(600, 600, 3)`` uint8 array, rows top to
    bottom) or ``"human"`` (a 600 x 600 pygame window updated at every reset and step and paced at
    ``metadata["render_fps"]``, which is ``round(1 / dt)``: 20 frames per second of simulated time
    by default, real time). The frame shows 6 m across (100 px per metre, a 1 m scale bar), centred
    on the midpoint of the follower and the true reference, x to the right and y up
    (:func:`auv_follow_env.rendering.to_pixel`): the target (red), the true reference (green
    circle), the follower (blue) with their last 20 s as trails, the time and the tracking error.
    On v1 it also shows the fixes the follower received in the trails' window at the received
    (noisy) target positions (orange circles; the newest a purple disc with its age, now minus its
    measurement time, as text) and a line with that age and the time since it arrived ("no fix
    received yet" before the first). Rendering only reads the env: episodes are the same with
    any ``render_mode``. Only pygame's display (``human``) and font modules are initialised, never
    its audio; ``rgb_array`` needs no display (headless machines), ``human`` on one needs
    ``SDL_VIDEODRIVER=dummy``. A video of each episode with gymnasium's wrapper (needs moviepy, in
    the ``dev`` extra)::

        env = gym.wrappers.RecordVideo(gym.make("AUVFollow-Easy-v1", render_mode="rgb_array"), "videos")

    ## Version History

    * v1: the acoustic link, random target, current and thrusters; the tiers Easy, Medium, Hard and
      Extreme, and the Leader tiers (Leader-Easy, -Medium, -Hard: a target that switches between hidden
      manoeuvre modes), each with published test seeds (``auv_follow_env.ALL_TIERS``).
    * v0: initial release (the paper's task; frozen).
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 20}

    def __init__(self, scenario: str = "S4", disturbance: str | None = None,
                 render_mode: str | None = None, *, version: str = "v0", tier: str | None = None,
                 sincos: str | None = None, fast_math: bool | None = None, link_trace: Any = None,
                 **overrides: Any) -> None:
        sincos = check_sincos(sincos, fast_math)
        if link_trace is not None and version != "v1":
            raise ValueError(f"link_trace={link_trace!r} is for the v1 ids (AUVFollow-*-v1): the v0 task has a "
                             f"constant delay and no link to replay")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} is unknown: valid modes are "
                             f"{self.metadata['render_modes']} or None")
        self.config = make_env_config(scenario, disturbance, version=version, tier=tier, **overrides)
        self.task_spec: TaskSpec = self.config.task_spec()
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.config.dt))}
        self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.task_spec.obs_dim,), np.float32)
        self._sim = BatchSim(self.config, 1, sincos, packed=True)
        #: how the step's sin/cos are computed: "simd" (default) or "libm" (the ``sincos`` keyword)
        self.sincos = sincos
        #: former name: ``sincos == "simd"``
        self.fast_math = sincos == "simd"
        self._step_one, self._buf = self._sim.step_one_call()
        # views of the sim's arrays, copied into each step's output
        self._obs0 = self._sim.obs[0]
        self._true_target = self._sim.truth[0, dyn.T_TARGET]
        self._true_reference = self._sim.truth[0, dyn.T_REF]
        self._follower_pose = self._sim.truth[0, dyn.T_FOLLOWER]
        self._dt = self.config.dt
        self._n_steps = self.config.n_steps
        self._started = False
        self._trails: deque | None = None
        self._fixes: deque | None = None  # v1: (x, y, measured at, arrived at) of the fixes received
        self._renderer = None
        #: the replay of ``link_trace`` (v1), else None: what the follower hears comes from the trace
        self._trace_link: TraceLink | None = None
        if link_trace is not None:
            self._trace_link = TraceLink(read_link_trace(link_trace), self._dt, self._n_steps)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise ValueError(f"seed={seed!r} is invalid: must be None or a non-negative int")
            seed = int(seed)
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"options={options!r} is invalid: must be a dict or None")
        super().reset(seed=seed)
        self._sim.reset(_IDX0, [self.np_random])
        self._started = True
        obs = self._sim.obs[0].copy()
        if self._trace_link is not None:
            self._trace_link.reset(self._sim, self._sim.truth[0, dyn.T_TARGET].copy())
            self._trace_link.observe(obs, self._sim, 0, self.fast_math)
        if self.render_mode is not None:
            self._trails = deque(maxlen=int(20.0 / self.config.dt))
            self._fixes = deque()
            self._record_trail()
        truth = self._sim.truth[0].copy()
        info = {"tracking_error": float(truth[12]), "time": 0.0, "true_target": truth[3:9],
                "true_reference": truth[9:12], "follower_pose": truth[0:3]}
        if self._sim.v1:
            info["condition"] = self._sim.condition(0)
        if self._trace_link is not None:
            info["link_trace"] = self._trace_link.trace.source
        if self.render_mode == "human":
            self.render()
        return obs, info

    def step(self, action: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if action.__class__ is not np.ndarray or action.dtype not in _FAST_DTYPES or action.shape != _SHAPE3 \
                or not action.flags.c_contiguous:
            action = check_action(action, (3,))
        # the kernel returns the step's scalars (rew[0], term[0], k[0], truth[0, T_ERR])
        bad, reward, terminated, k, err = self._step_one(self._buf, action)
        if bad >= 0:
            raise ValueError(f"action={action.tolist()} contains NaN or inf: the env was not changed")
        info = {"tracking_error": err, "time": k * self._dt, "true_target": self._true_target.copy(),
                "true_reference": self._true_reference.copy(), "follower_pose": self._follower_pose.copy()}
        obs = self._obs0.copy()
        trace = self._trace_link
        if trace is not None:
            trace.step(k, info["true_target"])
            if np.isfinite(self._sim.state[0]).all():  # (else the kernel zeroed the observation)
                trace.observe(obs, self._sim, k, self.fast_math)
        if terminated or k == self._n_steps:
            sim = self._sim
            info["episode_metrics"] = tracking_metrics(*sim.errors(0), self.config.steady_start_s)
            if sim.v1:
                info["link_stats"] = dict(trace.stats) if trace is not None else sim.link_stats(0)
        if self.render_mode is not None:
            self._record_trail()
            if self.render_mode == "human":
                self.render()
        return obs, reward, terminated, k >= self._n_steps and not terminated, info

    # --- rendering ------------------------------------------------------------------------
    def _record_trail(self) -> None:
        """Append the present poses to the trails and, on v1, a fix that arrived since the last call
        (read from the sim's held packet; nothing in the episode changes)."""
        tr = self._sim.truth[0]
        self._trails.append((tr[0], tr[1], tr[2], tr[3], tr[4], tr[5], tr[9], tr[10]))
        if self._sim.v1:
            dt = self.config.dt
            has, x, meas, arr = self._held_packet()
            if has and (not self._fixes or self._fixes[-1][3] != arr * dt):
                self._fixes.append((float(x[0]), float(x[1]), float(meas) * dt, float(arr) * dt))
            while self._fixes and self._fixes[0][3] < (self._sim.k[0] - self._trails.maxlen) * dt:
                self._fixes.popleft()  # (only the fixes of the trails' window)

    def _held_packet(self) -> tuple[bool, np.ndarray, int, int]:
        """The packet the follower holds: (any, measured x y psi u v r, measured at, arrived at [steps])."""
        t = self._trace_link
        if t is not None:
            return t.has, t.x, t.meas, t.arr
        p = self._sim.proc[0]
        return p[dyn.R_HAS] != 0.0, p[dyn.R_HX:dyn.R_HX + 6], int(p[dyn.R_HMEAS]), int(p[dyn.R_HARR])

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' "
                            "or 'human' to gym.make")
            return None
        if not self._started:
            raise RuntimeError("call reset() before render()")
        from auv_follow_env.rendering import Renderer

        if self._renderer is None:
            self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])
        return self._renderer.draw(list(self._trails), self._sim.k[0] * self.config.dt,
                                   float(self._sim.truth[0, dyn.T_ERR]),
                                   list(self._fixes) if self._sim.v1 else None)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _v1_tables() -> str:
    from auv_follow_env.params import CONDITION_FIELDS

    rows = ["", "    ## v1 parameters", "", "    | keyword | default | range | unit | meaning |",
            "    |---|---|---|---|---|"]
    for f in CONDITION_FIELDS:
        d = "scenario" if f.default is None else f"{f.default:g}"
        rng = f"{'(' if f.lo_open else '['}{f.lo:g}, {f.hi:g}]"
        rows.append(f"    | {f.name} | {d} | {rng} | {f.unit} | {f.doc} |")
    rows += ["", "    ## Tiers", ""] + ["    " + line if line else "" for line in tier_table_markdown().splitlines()]
    return "\n".join(rows) + "\n"


AUVFollowEnv.__doc__ = (AUVFollowEnv.__doc__ or "") + _v1_tables()
