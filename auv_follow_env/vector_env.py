"""AUVFollowVectorEnv: N envs in one Gymnasium ``VectorEnv`` (a batch-of-N shell over BatchSim).

The physics is :mod:`auv_follow_env.dynamics`, stepped for the whole batch by one kernel
call, exactly as :class:`~auv_follow_env.env.AUVFollowEnv` steps its batch of one. Env ``i``
of a vector env reset with ``seed=s`` reproduces, bit for bit, a single ``AUVFollowEnv``
reset with ``seed=s + i`` and then reset without a seed after each of its episodes.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from auv_follow_env import dynamics as dyn
from auv_follow_env.env import check_action
from auv_follow_env.metrics import METRIC_KEYS, history_metrics_into, steady_index
from auv_follow_env.params import TaskSpec
from auv_follow_env.sim import LINK_COUNTERS, STEP_ARRAYS, BatchSim, check_sincos
from auv_follow_env.tiers import make_env_config

__all__ = ["AUVFollowVectorEnv"]

#: where the step kernel's args hold the truth array
_TRUTH_ARG = STEP_ARRAYS.index("truth")
_LINK_COLS = np.array(list(LINK_COUNTERS.values()), dtype=np.int64)
_FAST_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
#: fewest envs for the automatic parallel path (parallel=None): below it one step of the batch
#: costs less than waking numba's threads
PARALLEL_MIN_ENVS = 256
_MIN_CHUNK = 64  # fewest envs per thread chunk when stepping in parallel


def _num_threads() -> int:
    """numba's thread count, without starting the threads (and loading the OpenMP runtime)
    if they are not running yet."""
    import numba
    from numba.np.ufunc import parallel

    if getattr(parallel, "_is_initialized", True):
        return numba.get_num_threads()
    return int(numba.config.NUMBA_NUM_THREADS)


def omp_wait_policy(load: float | None = None, cpus: int | None = None) -> str | None:
    """Choose how idle OpenMP workers wait, once, at the first threaded step of the process
    (the OpenMP runtime reads ``OMP_WAIT_POLICY`` when it loads); returns what it set.

    Nothing is changed if ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is set already. Otherwise:
    on a busy machine (1-min load average >= CPUs - 0.5, i.e. no core to spare) workers
    sleep (``PASSIVE``): spinning workers then take CPU time the stepping thread needs, and
    threaded steps ran 1.5-2x slower than serial ones with five busy processes on 2 cores.
    With a core free, libgomp's default (spin briefly, then sleep) is kept: a sleeping worker
    costs a wake-up per step, and in this virtual machine that made the threaded step about
    35 % slower (results/bench_vector.md, docs of ``parallel``).
    """
    if "OMP_WAIT_POLICY" in os.environ or "GOMP_SPINCOUNT" in os.environ:
        return None
    if load is None:
        try:
            load = os.getloadavg()[0]
        except OSError:  # no load average on this platform: be cautious
            load = math.inf
    cpus = cpus if cpus is not None else (os.cpu_count() or 1)
    if load >= cpus - 0.5:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        return "PASSIVE"
    return None


def _is_seed(s: object) -> bool:
    return isinstance(s, (int, np.integer)) and not isinstance(s, (bool, np.bool_)) and s >= 0


def _check_seeds(seed: object, n: int) -> list[int | None]:
    """Per-env seeds from ``seed`` (None, an int s -> s + i, or N ints / None), all checked
    before any generator changes."""
    if seed is None:
        return [None] * n
    if _is_seed(seed):
        return [int(seed) + i for i in range(n)]  # type: ignore[call-overload]
    if isinstance(seed, np.ndarray) and seed.ndim == 1:
        seed = seed.tolist()
    if not isinstance(seed, (list, tuple)):
        raise ValueError(f"seed={seed!r} is invalid: must be None, a non-negative int, or a list of num_envs={n} "
                         f"non-negative ints / None (got {type(seed).__name__})")
    if len(seed) != n:
        raise ValueError(f"seed is a sequence of length {len(seed)}: a list of seeds must have num_envs={n} entries")
    bad = [(i, s) for i, s in enumerate(seed) if s is not None and not _is_seed(s)]
    if bad:
        i, s = bad[0]
        raise ValueError(f"seed[{i}]={s!r} is invalid: each entry must be a non-negative int or None "
                         f"(no env was reseeded)")
    return [None if s is None else int(s) for s in seed]


_INFO_KEYS = ("tracking_error", "time", "true_target", "true_reference", "follower_pose")

#: most envs in one vector env (each env holds about 15 kB of arrays: 2**24 envs are 250 GB)
MAX_NUM_ENVS = 2**24


def check_autoreset_mode(mode: object) -> AutoresetMode:
    """``mode`` as an :class:`~gymnasium.vector.AutoresetMode`: a member, its value ("NextStep",
    "SameStep", "Disabled") or its name ("NEXT_STEP", ...); ``None`` is the default NEXT_STEP.

    Raises:
        ValueError: anything else, naming the allowed values.
    """
    if mode is None:
        return AutoresetMode.NEXT_STEP
    if isinstance(mode, AutoresetMode):
        return mode
    if isinstance(mode, str):
        for m in AutoresetMode:
            if mode in (m.value, m.name):
                return m
    raise ValueError(f"autoreset_mode={mode!r} is invalid: must be a gymnasium.vector.AutoresetMode "
                     f"({', '.join(f'{m.name} = {m.value!r}' for m in AutoresetMode)}: the member, its value or "
                     f"its name) or None (NEXT_STEP)")


class AUVFollowVectorEnv(VectorEnv):
    r"""``num_envs`` independent AUVFollow episodes stepped together by the numba kernels.

    The task, spaces, reward, termination and info of each env are those of
    :class:`~auv_follow_env.env.AUVFollowEnv` (see its docstring); this class only batches
    them. Made by ``gym.make_vec("AUVFollow-S4-v0", num_envs=N)`` (the registered
    ``vector_entry_point``) or directly.

    ## Spaces

    ``single_action_space`` / ``single_observation_space`` equal the single env's;
    ``action_space`` is ``Box(-1, 1, (N, 3), float32)`` and ``observation_space``
    ``Box(-inf, inf, (N, 16), float32)``. Actions are validated like the single env's:
    NaN/inf, a wrong shape or a non-numeric dtype raise ``ValueError`` and change nothing.

    ## Seeding

    Each env owns a ``np.random.Generator``, like the sub-envs of ``SyncVectorEnv``:
    ``reset(seed=s)`` gives env ``i`` the generator ``seeding.np_random(s + i)``; a list
    of N seeds (ints or ``None``) seeds env ``i`` with ``seed[i]``; ``None`` keeps an env's
    generator (or draws a random one on the first reset). Every episode of env ``i`` (first
    reset and autoresets alike) draws its parameters from env ``i``'s generator.

    ## Autoreset

    ``autoreset_mode`` (a keyword: ``gym.make_vec(id, num_envs=N, autoreset_mode=...)``;
    Gymnasium passes keywords, not ``vector_kwargs``, to a registered vector entry point) is
    the attribute ``autoreset_mode`` and ``metadata["autoreset_mode"]``, as on Gymnasium's own
    vector envs. The episodes are the same in every mode (same seeds, same actions on each
    episode's steps); only where the new episode starts differs:

    * ``AutoresetMode.NEXT_STEP`` (default, Gymnasium 1.x's): the step after env ``i``
      terminated or truncated resets it, ignoring its action, and returns its first
      observation with reward 0 and ``terminated = truncated = False``.
    * ``AutoresetMode.SAME_STEP`` (what TorchRL needs): an env that ends is reset within the
      same step. That step returns its reward, ``terminated`` and ``truncated``, and the
      **new** episode's first observation; the last observation of the ended episode is in
      ``info["final_obs"]`` (an object array of N entries, ``None`` for the envs that did not
      end) and the step's info of the ended envs in ``info["final_info"]`` (a dict like the
      info below, with ``episode_metrics`` and on v1 ``link_stats``), each with its mask
      ``_final_obs`` / ``_final_info``, as ``SyncVectorEnv`` gives them. The top-level info of an
      env that was reset is its new episode's (on v1 with ``condition``).
    * ``AutoresetMode.DISABLED``: nothing is reset by ``step``; reset the envs that ended with
      ``reset(options={"reset_mask": terminated | truncated})`` before the next step (a step
      with an ended env left raises ``RuntimeError`` and changes nothing).

    Episodes truncate at ``episode_s`` (``config.n_steps`` steps) inside the env: vector envs have no
    ``TimeLimit`` wrapper. After an env's autoreset (or a reset by mask without seeds under
    DISABLED) its next episode is drawn from its
    generator and started (the target's and link's warm-up) ahead, together with other envs',
    and copied in at its next autoreset: the same episodes in the same order as drawing each at
    its reset (a reseeded env's early draw is dropped), at less cost per autoreset. The
    generators therefore run up to one episode ahead of the envs: seed, do not share them.

    ## Info

    A dict of arrays, each with its Gymnasium boolean mask ``_key``: ``tracking_error``
    (N,), ``time`` (N,), ``true_target`` (N, 6), ``true_reference`` (N, 3),
    ``follower_pose`` (N, 3) (after an autoreset, those of the new episode's start). On a
    step where some episodes ended, ``episode_metrics`` is a dict of (N,) arrays
    (:data:`~auv_follow_env.metrics.METRIC_KEYS`, NaN for the envs that did not end) and
    ``_episode_metrics`` marks the envs that did.

    ## Arguments

    ``num_envs`` and the single env's arguments (``scenario``, ``disturbance``, overrides;
    see :func:`~auv_follow_env.params.make_config`). ``render_mode`` must be ``None``.
    ``max_episode_steps`` is what ``gym.make_vec`` passes from the registration; it must
    equal ``episode_s / dt`` (pass it along with ``episode_s`` when you change the latter).
    ``parallel`` chooses how a step runs: ``None`` (default) steps the batch on numba's
    threads when it has at least :data:`PARALLEL_MIN_ENVS` (256) envs and numba has more
    than one thread, serially otherwise; ``True`` uses the threads whenever the batch splits
    into at least two chunks of 64 envs; ``False`` never. Threaded steps are one parallel
    region per step (:func:`~auv_follow_env.dynamics.step_kernel_parallel`: contiguous
    slices of the batch in a ``prange`` loop, the same per-env code), so the results are
    bit-identical either way; the speed-up is at most the number of free cores. Resets of two
    blocks of envs or more, and the episodes started ahead, then run on the threads too
    (:func:`~auv_follow_env.dynamics.reset_kernel_parallel`). The threaded
    kernel is compiled on its first use and then cached on disk like the others;
    ``NUMBA_NUM_THREADS`` sets the thread count. Choosing the threads may set
    ``OMP_WAIT_POLICY=PASSIVE`` in the process environment, if neither it nor
    ``GOMP_SPINCOUNT`` is set and the machine is busy then (:func:`omp_wait_policy`): idle
    OpenMP workers sleep rather than spin when no core is free, and spin briefly (libgomp's
    default) when one is.
    ``sincos`` (default ``"simd"``; ``"libm"`` for glibc's sin/cos) and its former name
    ``fast_math``: see :class:`~auv_follow_env.env.AUVFollowEnv`. ``num_envs`` is at most
    :data:`MAX_NUM_ENVS`; a batch that does not fit in memory is a ``ValueError`` naming it. A
    keyword that is neither an argument nor an override is a ``TypeError`` naming it
    (:class:`~auv_follow_env.params.UnknownKeywordError`).
    """

    metadata = {"render_modes": [], "render_fps": 20, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, scenario: str = "S4", disturbance: str | None = None,
                 render_mode: str | None = None, max_episode_steps: int | None = None,
                 parallel: bool | None = None, *, version: str = "v0", tier: str | None = None,
                 sincos: str | None = None, fast_math: bool | None = None,
                 autoreset_mode: AutoresetMode | str | None = None, **overrides: Any) -> None:
        sincos = check_sincos(sincos, fast_math)
        if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, (int, np.integer)) \
                or not 1 <= num_envs <= MAX_NUM_ENVS:
            shown = repr(num_envs) if len(repr(num_envs)) <= 40 else f"{repr(num_envs)[:20]}..."
            raise ValueError(f"num_envs={shown} is invalid: must be an integer in [1, {MAX_NUM_ENVS}]")
        #: how envs that end are reset (:class:`~gymnasium.vector.AutoresetMode`; see the class docstring)
        self.autoreset_mode = check_autoreset_mode(autoreset_mode)
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r} is not supported by the vector env: pass "
                             f"None (render a single AUVFollowEnv instead)")
        if "link_trace" in overrides:
            raise ValueError("link_trace is not a vector-env keyword: a trace replays one episode's link; use "
                             "gym.make(id, link_trace=FILE) (the single env)")
        self.config = make_env_config(scenario, disturbance, version=version, tier=tier, **overrides)
        n_steps = self.config.n_steps
        if max_episode_steps is not None and max_episode_steps != n_steps:
            raise ValueError(
                f"max_episode_steps={max_episode_steps} disagrees with episode_s={self.config.episode_s} s "
                f"({n_steps} steps of {self.config.dt} s): pass max_episode_steps={n_steps} to "
                f"gym.make_vec, or the matching episode_s")
        self.num_envs = int(num_envs)
        self.render_mode = None
        self.task_spec: TaskSpec = self.config.task_spec()
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.config.dt)),
                         "autoreset_mode": self.autoreset_mode}
        self.single_action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.single_observation_space = spaces.Box(-np.inf, np.inf, (self.task_spec.obs_dim,), np.float32)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)

        try:
            self._sim = BatchSim(self.config, self.num_envs, sincos, draw_ahead=True)  # (its generators are ours)
        except MemoryError as exc:
            raise ValueError(f"num_envs={self.num_envs} does not fit in this machine's memory ({exc}): "
                             f"use fewer envs") from None
        #: how the step's sin/cos are computed: "simd" (default) or "libm" (the ``sincos`` keyword)
        self.sincos = sincos
        #: former name: ``sincos == "simd"``
        self.fast_math = sincos == "simd"
        self._kernel, self._args = self._sim.step_call()
        if parallel is not None and not isinstance(parallel, (bool, np.bool_)):
            raise ValueError(f"parallel={parallel!r} is invalid: pass None (automatic), True or False")
        self._parallel = None
        threads = _num_threads() if parallel is not False else 1
        if threads > 1 and (parallel or self.num_envs >= PARALLEL_MIN_ENVS):
            # a few chunks per thread balance the load when other processes share the cores
            chunks = min(4 * threads, self.num_envs // _MIN_CHUNK)
            if chunks >= 2:
                self._parallel = (dyn.step_kernel_parallel, chunks)
                self._sim.reset_on_threads(chunks)
                omp_wait_policy()
        #: whether steps run on numba's threads (the resolved ``parallel`` argument)
        self.parallel = self._parallel is not None
        self._n_steps = n_steps
        self._steady0 = steady_index(self._sim.sample_times, self.config.steady_start_s)
        self._dt = self.config.dt
        self._rngs: list[np.random.Generator | None] = [None] * self.num_envs
        self._autoreset = np.zeros(self.num_envs, dtype=np.bool_)  # ended last step
        self._autoreset_idx = np.zeros(0, dtype=np.int64)
        self._started = False

    # --- Gymnasium API --------------------------------------------------------------------
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start new episodes in every env (or in ``options["reset_mask"]``'s envs).

        Args:
            seed: ``None`` (keep each env's generator), an int ``s`` (env ``i`` gets
                ``s + i``) or a list of N ints / ``None``.
            options: optionally ``{"reset_mask": bool array (N,)}``: reset only those envs
                (as ``SyncVectorEnv``); the info masks mark them. Under
                ``AutoresetMode.DISABLED`` this is how the envs that ended are reset.

        Returns:
            observations (N, 16) float32 and the info dict of arrays.
        """
        n = self.num_envs
        seeds = _check_seeds(seed, n)
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"options={options!r} is invalid: must be a dict or None")
        mask = np.ones(n, dtype=np.bool_)
        if options is not None and "reset_mask" in options:
            mask = options["reset_mask"]
            if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (n,):
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({n},), got {mask!r}")
            if not mask.any():
                raise ValueError("options['reset_mask'] resets no env: at least one entry must be True")
            if not self._started and not mask.all():
                raise ValueError("options['reset_mask'] must select every env on the first reset")
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            super().reset(seed=int(seed))  # the vector env's own generator (unused by the physics)
        idx = np.flatnonzero(mask)
        for i in idx:
            if seeds[i] is not None or self._rngs[i] is None:
                self._rngs[i] = seeding.np_random(seeds[i])[0]
        self._copy_truth()  # (the other envs keep their rows)
        # under DISABLED a reset by mask without seeds is the autoreset: start the next episodes ahead
        auto = self.autoreset_mode is AutoresetMode.DISABLED and self._started and all(seeds[i] is None for i in idx)
        self._sim.reset(idx, [self._rngs[i] for i in idx], auto=auto)
        self._autoreset[idx] = False
        self._autoreset_idx = np.flatnonzero(self._autoreset)
        self._started = True
        info = self._info(mask if not mask.all() else None)
        if self._sim.v1:
            info["condition"], info["_condition"] = self._conditions(mask)
        return self._sim.obs.copy(), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance every env one control step (envs whose episode ended last step reset).

        Args:
            actions: (N, 3) in [-1, 1] (clipped), any real dtype.

        Returns:
            observations (N, 16) float32, rewards (N,) float64, terminated (N,) bool,
            truncated (N,) bool, info dict of arrays.

        Under ``AutoresetMode.SAME_STEP`` the envs that end are reset before it returns (their
        last observation and info in ``info["final_obs"]`` / ``info["final_info"]``); under
        ``DISABLED`` they are not reset.

        Raises:
            RuntimeError: before the first :meth:`reset`, or under ``DISABLED`` while an env that
                ended has not been reset (nothing is changed).
            ValueError: NaN/inf, wrong shape or non-numeric actions (nothing is changed).
        """
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self.autoreset_mode is not AutoresetMode.NEXT_STEP:
            return self._step_now(actions)
        n = self.num_envs
        a = actions
        if type(a) is not np.ndarray or a.shape != (n, 3) or a.dtype not in _FAST_DTYPES \
                or not a.flags.c_contiguous:
            a = check_action(a, (n, 3))
        ended = self._autoreset_idx
        if a.dtype != np.float64 or ended.size:
            # the kernels take float64 only (float32 -> float64 is exact: the same forces), so numba
            # compiles one specialisation of them, not one more per action dtype (seconds each);
            # astype copies, so the ended envs' actions are zeroed in our copy, not the caller's
            a = a.astype(np.float64)
            a[ended] = 0.0  # their actions are ignored (they reset), even if not finite
        flat = a.reshape(-1)
        sim = self._sim
        # the step writes every env's truth row (the info's arrays) into a new array: no copy of
        # the old one to hand out, and the info returned before is never written again
        truth = np.empty_like(sim.truth)
        args = self._args[:_TRUTH_ARG] + (truth,) + self._args[_TRUTH_ARG + 1:]
        if self._parallel is not None:
            bad = self._parallel[0](*args, flat, self._parallel[1])
        else:
            bad = self._kernel(*args, flat)
        if bad >= 0:
            raise ValueError(f"actions[{bad}]={np.asarray(a[bad]).tolist()} contains NaN or inf: "
                             f"no env was changed")
        sim.truth, self._args = truth, args
        terminated = sim.term.copy()
        truncated = sim.k >= self._n_steps
        truncated &= ~terminated
        rewards = sim.rew.copy()
        metrics = None
        link = None
        done_now = (terminated | truncated) & ~self._autoreset
        if sim.v1 and done_now.any():
            link = self._link_stats(done_now)
        if ended.size:
            sim.reset(ended, [self._rngs[i] for i in ended], auto=True)
            rewards[ended] = 0.0
            terminated[ended] = False
            truncated[ended] = False
        done = terminated | truncated
        if done.any():
            metrics = self._episode_metrics(done)
        self._autoreset = done
        self._autoreset_idx = np.flatnonzero(done)
        info = self._info(None)
        if metrics is not None:
            info["episode_metrics"], info["_episode_metrics"] = metrics, done.copy()
        if link is not None:
            info["link_stats"], info["_link_stats"] = link, done.copy()
        if sim.v1 and ended.size:
            started = np.zeros(self.num_envs, dtype=np.bool_)
            started[ended] = True
            info["condition"], info["_condition"] = self._conditions(started)
        return sim.obs.copy(), rewards, terminated, truncated, info

    def _step_now(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step under SAME_STEP (envs that end are reset at once) or DISABLED (they wait for
        ``reset(options={"reset_mask": ...})``). No env is being autoreset when it starts, so every
        env is stepped with its action; the physics is NEXT_STEP's."""
        n = self.num_envs
        same = self.autoreset_mode is AutoresetMode.SAME_STEP
        if self._autoreset_idx.size:  # (only under DISABLED)
            raise RuntimeError(
                f"envs {self._autoreset_idx.tolist()} ended at the last step and were not reset: with "
                f"autoreset_mode=DISABLED call reset(options={{'reset_mask': terminated | truncated}}) first "
                f"(nothing was stepped)")
        a = actions
        if type(a) is not np.ndarray or a.shape != (n, 3) or a.dtype not in _FAST_DTYPES \
                or not a.flags.c_contiguous:
            a = check_action(a, (n, 3))
        if a.dtype != np.float64:
            a = a.astype(np.float64)  # (float32 -> float64 is exact; one compiled specialisation)
        sim = self._sim
        truth = np.empty_like(sim.truth)
        args = self._args[:_TRUTH_ARG] + (truth,) + self._args[_TRUTH_ARG + 1:]
        if self._parallel is not None:
            bad = self._parallel[0](*args, a.reshape(-1), self._parallel[1])
        else:
            bad = self._kernel(*args, a.reshape(-1))
        if bad >= 0:
            raise ValueError(f"actions[{bad}]={np.asarray(a[bad]).tolist()} contains NaN or inf: "
                             f"no env was changed")
        sim.truth, self._args = truth, args
        terminated = sim.term.copy()
        truncated = sim.k >= self._n_steps
        truncated &= ~terminated
        rewards = sim.rew.copy()
        done = terminated | truncated
        if not done.any():
            self._autoreset[:] = False
            self._autoreset_idx = np.zeros(0, dtype=np.int64)
            return sim.obs.copy(), rewards, terminated, truncated, self._info(None)
        ended = {"episode_metrics": self._episode_metrics(done)}
        if sim.v1:
            ended["link_stats"] = self._link_stats(done)
        if not same:  # DISABLED: the ended envs keep their last state until the caller resets them
            self._autoreset = done
            self._autoreset_idx = np.flatnonzero(done)
            info = self._info(None)
            for key, value in ended.items():
                info[key], info["_" + key] = value, done.copy()
            return sim.obs.copy(), rewards, terminated, truncated, info
        # SAME_STEP: the ended episodes' last observation and info, then their resets
        ids = np.flatnonzero(done)
        final_obs = np.full(n, None, dtype=object)
        for i in ids.tolist():
            final_obs[i] = sim.obs[i].copy()
        final_info = self._info(done, truth=truth.copy(), k=sim.k.copy())
        for key, value in ended.items():
            final_info[key], final_info["_" + key] = value, done.copy()
        sim.reset(ids, [self._rngs[i] for i in ids], auto=True)
        self._autoreset[:] = False
        self._autoreset_idx = np.zeros(0, dtype=np.int64)
        info = self._info(None)
        info["final_obs"], info["_final_obs"] = final_obs, done.copy()
        info["final_info"], info["_final_info"] = final_info, done.copy()
        if sim.v1:
            info["condition"], info["_condition"] = self._conditions(done)
        return sim.obs.copy(), rewards, terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release (no renderer, no worker processes)."""

    # --- helpers --------------------------------------------------------------------------
    def _copy_truth(self) -> None:
        """Give the sim a copy of its truth array (a reset of some envs keeps the others' rows), so
        the info handed out before is never written again. (The observations are copied out
        instead: a reset of some envs returns the others' last observations, which must not be
        what a caller made of the array it was given.)"""
        sim = self._sim
        sim.truth = sim.truth.copy()
        self._kernel, self._args = sim.step_call()

    def _info(self, mask: np.ndarray | None, truth: np.ndarray | None = None,
              k: np.ndarray | None = None) -> dict[str, Any]:
        """The per-step info arrays (views into the truth array of this step or reset, which the
        sim does not write again; or into ``truth`` at steps ``k``, copies kept before a reset)."""
        sim = self._sim
        truth = sim.truth if truth is None else truth
        k = sim.k if k is None else k
        info: dict[str, Any] = {
            "tracking_error": truth[:, 12], "time": k * self._dt, "true_target": truth[:, 3:9],
            "true_reference": truth[:, 9:12], "follower_pose": truth[:, 0:3]}
        m = np.ones(self.num_envs, dtype=np.bool_) if mask is None else mask
        for key in _INFO_KEYS:
            info["_" + key] = m.copy()
        return info

    def _conditions(self, mask: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """v1: the conditions drawn for the envs in ``mask`` (NaN / None elsewhere), with the mask."""
        return self._sim.conditions(mask), mask.copy()

    def _link_stats(self, done: np.ndarray) -> dict[str, np.ndarray]:
        """v1: packet counts of the episodes that ended (-1 elsewhere)."""
        ids = np.flatnonzero(done)
        counts = self._sim.proc[ids][:, _LINK_COLS].astype(np.int64)  # (as int(): toward zero)
        out = {}
        for j, key in enumerate(LINK_COUNTERS):
            out[key] = np.full(self.num_envs, -1, dtype=np.int64)
            out[key][ids] = counts[:, j]
        return out

    def _episode_metrics(self, done: np.ndarray) -> dict[str, np.ndarray]:
        """The paper's metrics of the episodes that ended (NaN elsewhere), with masks."""
        sim = self._sim
        ids = np.flatnonzero(done)
        rows = np.full((len(METRIC_KEYS), self.num_envs), np.nan)
        history_metrics_into(sim.err_hist, ids, np.minimum(sim.k[ids], self.config.n_steps), self._steady0, rows)
        out: dict[str, np.ndarray] = dict(zip(METRIC_KEYS, rows, strict=True))
        for key in METRIC_KEYS:
            out["_" + key] = done.copy()
        return out
