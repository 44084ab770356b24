"""The single env's step: the batched kernel's :func:`~auv_follow_env.dynamics.step_range` for
one env, called with two arguments instead of thirteen.

At N = 1 numba's dispatch of the thirteen arrays of :func:`~auv_follow_env.dynamics.step_kernel`
costs about as much as the physics (each array argument is unboxed separately). Here all the
arrays of a one-env :class:`~auv_follow_env.sim.BatchSim` are views of one float64 buffer
(:func:`packed_arrays`); :func:`step_one` takes that buffer and the action, rebuilds the same
views inside numba (the same array types) and returns the step's scalars, so the Python shell
reads no numpy scalars. The step itself is ``step_range``'s own code (not a copy of its source:
a second dispatcher of the same Python function) whose block functions ``advance_block`` and
``gather_block`` are called with the lane count as the literal 1, so numba compiles them for a
block of one lane, where every loop over lanes is a single iteration known at compile time.
``advance_block`` is its one-lane copy (``_ONE_LANE``): the lane's RK4 step with libm beyond
SMALL_ANGLE at once, where the block path runs small-angle polynomials in a SIMD loop and
redoes the rare lanes beyond it; for every lane both give the same operations, and a single
env compiles one RK4 step instead of two (cold start). Same operations in the same order:
results are bit-identical to the vector env's (tests/test_kernel_one.py compares every array
after every step, also with heading increments beyond SMALL_ANGLE). :func:`reset_one` is
``reset_kernel``'s code in the same way, sharing the one-lane ``advance_block`` with the step,
so a single env compiles one specialisation of it (cold start).

Buffer layout (float64 slots): a header (queue capacity, observation length, history length and
offset), then cfg, state, k (int64), rs (uint64), proc, params, truth, rew, term (bool), obs
(float32, up to 20), err_stage, the step's work buffer, queue, err_hist (from a 64-byte boundary).
The work buffer (:func:`~auv_follow_env.dynamics.work_buffer`'s NK rows of BLOCK slots, of which
the one lane uses the first) stays from step to step: no allocation per step, and the tones'
rotation factors, keyed by their angle, are reused while the angle is the same, as in a block
of the vector env (the same values: bit-identical). The step took 1.94 -> 1.70 us (S4-v0) and
2.13 -> 1.83 us (Hard-v1) with it (`step_one` timed alone, best of five alternating runs).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from auv_follow_env import dynamics as dyn

__all__ = ["packed_arrays", "step_one", "reset_one"]

_NC, _NR, _NP, _NT, _NQ = dyn.NC, dyn.NR, dyn.NP, dyn.NT, dyn.NQ
_OBS_SLOTS = 10  # float64 slots for the float32 observation (up to 20 values)
O_HDR = 0  # header: queue capacity, obs length, err_hist length, err_hist offset
O_CFG = 4
O_ST = O_CFG + _NC
O_K = O_ST + 9
O_RS = O_K + 1
O_PROC = O_RS + 1
O_PAR = O_PROC + _NR
O_TR = O_PAR + _NP
O_REW = O_TR + _NT
O_TERM = O_REW + 1
O_OBS = O_TERM + 1
O_STG = O_OBS + _OBS_SLOTS  # err_stage (8 samples)
O_WK = O_STG + 8  # the step's work buffer (dynamics.work_buffer), kept from step to step
O_Q = O_WK + dyn.NK * dyn.BLOCK


def packed_arrays(q: int, d: int, h: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(buffer, arrays): zeroed one-env arrays of BatchSim (state, k, proc, queue, rs, params,
    cfg, obs, truth, err_hist, err_stage, rew, term) with their usual shapes and dtypes, all views of
    ``buffer``; ``q`` the queue capacity, ``d`` the observation length, ``h`` the steps of an
    episode (err_hist columns)."""
    if not 0 < d <= 2 * _OBS_SLOTS:
        raise ValueError(f"observation length {d} does not fit the packed layout")
    buf = np.zeros(O_Q + q * _NQ + h + 8)
    # err_hist from the first 64-byte cache line after the queue (as sim._aligned_zeros); its
    # offset, which depends on the buffer's address, is in the header
    o_e = O_Q + q * _NQ
    o_e += (-(buf.ctypes.data + 8 * o_e) % 64) // 8
    buf[O_HDR:O_HDR + 4] = q, d, h, o_e
    buf[O_WK + dyn.WK_KEYS[0]:O_WK + dyn.WK_KEYS[1]] = np.nan  # (as dynamics.work_buffer)
    arrays = {
        "state": buf[O_ST:O_ST + 9].reshape(1, 9),
        "k": buf[O_K:O_K + 1].view(np.int64),
        "proc": buf[O_PROC:O_PROC + _NR].reshape(1, _NR),
        "queue": buf[O_Q:O_Q + q * _NQ].reshape(1, q, _NQ),
        "rs": buf[O_RS:O_RS + 1].view(np.uint64),
        "params": buf[O_PAR:O_PAR + _NP].reshape(1, _NP),
        "cfg": buf[O_CFG:O_CFG + _NC],
        "obs": buf[O_OBS:O_OBS + _OBS_SLOTS].view(np.float32)[:d].reshape(1, d),
        "truth": buf[O_TR:O_TR + _NT].reshape(1, _NT),
        "err_hist": buf[o_e:o_e + h].reshape(1, h),
        "err_stage": buf[O_STG:O_STG + 8].reshape(1, 8),
        "rew": buf[O_REW:O_REW + 1],
        "term": buf[O_TERM:O_TERM + 1].view(np.bool_)[:1],
    }
    return buf, arrays


@intrinsic
def _address(typingctx, arr, offset):
    """The address of element ``offset`` of the 1-D array ``arr`` (a voidptr)."""
    sig = types.voidptr(arr, offset)

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        off = context.cast(builder, args[1], sig.args[1], types.intp)
        return builder.bitcast(cgutils.gep(builder, ary.data, off), cgutils.voidptr_t)

    return sig, codegen


@njit(cache=True, inline="always")
def _views(buf):
    """The arrays of :func:`packed_arrays`, in :func:`~auv_follow_env.dynamics.step_kernel`'s
    order (carrays over ``buf``'s memory: no reshapes, no reference counts; valid while ``buf``
    is, i.e. within the call)."""
    q = int(buf[O_HDR])
    d = int(buf[O_HDR + 1])
    h = int(buf[O_HDR + 2])
    o_e = int(buf[O_HDR + 3])
    f8 = np.float64
    return (carray(_address(buf, O_ST), (1, 9), f8), carray(_address(buf, O_K), 1, np.int64),
            carray(_address(buf, O_PROC), (1, _NR), f8), carray(_address(buf, O_Q), (1, q, _NQ), f8),
            carray(_address(buf, O_RS), 1, np.uint64), carray(_address(buf, O_PAR), (1, _NP), f8),
            carray(_address(buf, O_CFG), _NC, f8), carray(_address(buf, O_OBS), (1, d), np.float32),
            carray(_address(buf, O_TR), (1, _NT), f8), carray(_address(buf, o_e), (1, h), f8),
            carray(_address(buf, O_STG), (1, 8), f8), carray(_address(buf, O_REW), 1, f8),
            carray(_address(buf, O_TERM), 1, np.bool_))


#: dynamics.advance_block with its one-lane path (``_ONE_LANE``): the lane's RK4 step compiled once,
#: with libm beyond SMALL_ANGLE, instead of the block path's SIMD copy plus the redo (cold start)
_advance_block_one = dyn.recompiled(dyn.advance_block.py_func, "advance_block_one", {"_ONE_LANE": True},
                                    cache=False, error_model="numpy", **dyn.INTERNAL)


@njit(inline="always")
def _advance_one(wk, dt, nsub, m, fast):
    """:func:`~auv_follow_env.dynamics.advance_block` of a one-lane block, with the lane count a
    compile-time constant (numba compiles a specialisation for the literal 1, where every loop
    over lanes is one iteration known at compile time; the single env's reset and step share it)."""
    if m != 1:
        raise AssertionError("kernel_one: a block of one env expected")
    _advance_block_one(wk, dt, nsub, 1, fast)


@njit(inline="always")
def _gather_one(state, p, a, m, wk):
    """:func:`~auv_follow_env.dynamics.gather_block` of one env (the lane count a constant)."""
    if m != 1:
        raise AssertionError("kernel_one: a block of one env expected")
    dyn.gather_block(state, p, a, 1, wk)


def _rebound(disp, **subs):
    """A new dispatcher compiled from ``disp``'s own Python function (the same code object), with
    the globals ``subs`` replaced (not cached on its own: step_one's cache holds it)."""
    f = disp.py_func
    opts = {k: v for k, v in disp.targetoptions.items() if k != "nopython"}
    return dyn.recompiled(f, f"{f.__qualname__}_one", subs, **{**opts, "cache": False})


#: dynamics.step_range, the same code, calling the one-lane block functions, and calling (not
#: inlining) the per-env functions that the reset calls too: compiled once for both (cold start)
_step_range_one = _rebound(dyn.step_range, advance_block=_advance_one, gather_block=_gather_one,
                           link_tick=dyn._link_tick_r, _observe_dp=dyn._observe_dp_r,
                           update_processes_block=dyn._update_processes_block_r, thrusters=dyn._thrusters_r,
                           refresh_trig=dyn._refresh_trig_r, refresh_trig_block=dyn._refresh_trig_block_r,
                           _load_random_forcing=dyn._load_random_forcing_r)
#: dynamics.reset_range, the same code, with the one-lane RK4 block (of one env only)
_reset_range_one = _rebound(dyn.reset_range, advance_block=_advance_one)


def _build():
    # numba's on-disk cache is keyed on this file only, but step_one compiles dynamics' code into
    # itself: the hash of dynamics.py, a closure variable, is part of the cache key, so an edit
    # there recompiles step_one instead of loading a stale one
    dynamics_hash = hashlib.sha256(Path(dyn.__file__).read_bytes()).hexdigest()

    def step_one(buf, action):
        """One control step of the env packed in ``buf`` (:func:`packed_arrays`) under the flat
        action (3,) in [-1, 1]: :func:`~auv_follow_env.dynamics.step_kernel` for one env.

        Returns (bad, reward, terminated, k, tracking error): bad is -1, or 0 if the action is
        not finite (then nothing was changed and the other values are meaningless); the rest
        are rew[0], term[0], k[0] and truth[0, T_ERR] after the step.
        """
        if len(dynamics_hash) == 0:  # (never: makes the hash a closure variable of the kernel)
            return -2, 0.0, False, 0, 0.0
        state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term = _views(buf)
        bad = dyn.first_bad_action(action)
        if bad >= 0:
            return bad, 0.0, False, 0, 0.0
        _step_range_one(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action,
                        0, 1, carray(_address(buf, O_WK), dyn.NK * dyn.BLOCK, np.float64))
        return -1, rew[0], term[0], k[0], truth[0, dyn.T_ERR]

    def reset_one(buf, seed, direction):
        """A new episode of the env packed in ``buf`` (its params row must be set):
        :func:`~auv_follow_env.dynamics.reset_kernel` for one env, seeding its generator with
        ``seed`` and the Gauss-Markov current's direction ``direction`` [rad]."""
        if len(dynamics_hash) == 0:  # (never: as in step_one)
            return
        state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term = _views(buf)
        idx = np.zeros(1, dtype=np.int64)
        seeds = np.full(1, seed, dtype=np.int64)
        directions = np.full(1, direction)
        _reset_range_one(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth, dyn.work_buffer(True))

    return njit(cache=True)(step_one), njit(cache=True)(reset_one)


step_one, reset_one = _build()
