"""What the follower hears on one AUVFollow-Hard-v1 episode, against the truth.

Writes ``results/link_hard.png``: (a) the true target path, the fixes the follower received
(noisy, stale) and the sends that were lost; (b) the age of the newest packet over time with
the arrivals and lost sends marked; (c) how far the newest fix is from the true target now,
and the follower's tracking error.

Usage: ``python -m experiments.link_figure [--seed S] [--policy PROPOSED] [--out PATH]``.
The seed defaults to a training-range seed (not one of the tier's test seeds).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import auv_follow_env  # noqa: E402,F401
from auv_follow_env import dynamics as dyn  # noqa: E402
from auv_follow_env.layout import OBS_INDEX_V1  # noqa: E402
from controllers import make_controller  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    seed: int = 12  #: env seed (training range; never a test seed)
    policy: str = "PROPOSED"  #: scripted controller that drives the follower
    env_id: str = "AUVFollow-Hard-v1"  #: v1 id
    out: Path = ROOT / "results" / "link_hard.png"  #: PNG output


def record(args: Args) -> dict[str, np.ndarray]:
    """Step one episode; read the link's counters to find sends and losses (white-box, for the plot)."""
    env = gym.make(args.env_id)
    policy = make_controller(args.policy, env.unwrapped.task_spec)
    obs, info = env.reset(seed=args.seed)
    sim = env.unwrapped._sim
    dt = env.unwrapped.config.dt
    rows, sends, done = [], [], False
    sent, lost = sim.proc[0, dyn.R_SENT], sim.proc[0, dyn.R_LOST]
    k = 0
    while not done:
        o = obs
        c, s = o[3], o[4]
        pose = info["follower_pose"]
        has = o[OBS_INDEX_V1["has_packet"]] == 1.0
        fx = pose[0] + c * o[5] - s * o[6] if has else np.nan
        fy = pose[1] + s * o[5] + c * o[6] if has else np.nan
        rows.append((k * dt, *info["true_target"][:2], *pose[:2], fx, fy, o[OBS_INDEX_V1["packet_age"]],
                     o[OBS_INDEX_V1["new_packet"]], info["tracking_error"]))
        action, _ = policy.predict(obs)
        obs, _, term, trunc, info = env.step(action)
        k += 1
        done = term or trunc
        if sim.proc[0, dyn.R_SENT] > sent:
            sends.append((k * dt, *info["true_target"][:2], float(sim.proc[0, dyn.R_LOST] > lost)))
        sent, lost = sim.proc[0, dyn.R_SENT], sim.proc[0, dyn.R_LOST]
    cond = info.get("link_stats", {})
    a = np.array(rows)
    return {"t": a[:, 0], "tx": a[:, 1], "ty": a[:, 2], "x": a[:, 3], "y": a[:, 4], "fx": a[:, 5], "fy": a[:, 6],
            "age": a[:, 7], "new": a[:, 8], "err": a[:, 9], "sends": np.array(sends).reshape(-1, 4),
            "stats": cond, "condition": env.unwrapped._sim.condition(0)}


def plot(d: dict, args: Args) -> None:
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.8), gridspec_kw={"width_ratios": [1.1, 1, 1]})
    new = d["new"] == 1.0
    s = d["sends"]
    lost = s[:, 3] == 1.0 if len(s) else np.zeros(0, bool)
    a = ax[0]
    a.plot(d["tx"], d["ty"], "k-", lw=1.5, label="true target")
    a.plot(d["x"], d["y"], "-", color="tab:blue", lw=1, label=f"follower ({args.policy})")
    a.plot(d["fx"][new], d["fy"][new], "o", ms=4, color="tab:green", label="fix received (noisy, stale)")
    if lost.any():
        a.plot(s[lost, 1], s[lost, 2], "x", ms=7, color="tab:red", label="target when a lost packet was sent")
    a.set_aspect("equal", "datalim")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.set_title("(a) paths and fixes")
    a.legend(fontsize=8, loc="best")
    a = ax[1]
    a.plot(d["t"], d["age"], "-", color="tab:green", lw=1, label="age of the newest packet")
    a.plot(d["t"][new], d["age"][new], "o", ms=3, color="tab:green", label="arrival")
    if len(s):
        a.vlines(s[~lost, 0], 0, 0.25, color="0.5", lw=0.8, label="send")
        a.vlines(s[lost, 0], 0, 0.6, color="tab:red", lw=1.5, label="send, lost")
    a.set_xlabel("t [s]")
    a.set_ylabel("age [s]")
    a.set_ylim(bottom=0)
    a.set_title("(b) what the follower knows, and how old it is")
    a.legend(fontsize=8, loc="upper left", ncol=2)
    a = ax[2]
    stale = np.hypot(d["fx"] - d["tx"], d["fy"] - d["ty"])
    a.plot(d["t"], stale, "-", color="tab:green", lw=1, label="|newest fix - true target now|")
    a.plot(d["t"], d["err"], "-", color="tab:blue", lw=1, label="tracking error (true reference)")
    a.set_xlabel("t [s]")
    a.set_ylabel("[m]")
    a.set_ylim(bottom=0)
    a.set_title("(c) information lag vs tracking error")
    a.legend(fontsize=8)
    c, st = d["condition"], d["stats"]
    fig.suptitle(f"{args.env_id}, seed {args.seed}: fix every {c['update_period_s']:.2f} s, latency "
                 f"{c['latency_s']:.2f} +- {c['latency_spread_s']:.2f} s, loss {c['loss_prob']:.0%} i.i.d. + bursts; "
                 f"{st.get('sent', 0)} sent, {st.get('lost', 0)} lost, {st.get('arrived', 0)} arrived",
                 fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--seed", type=int, default=Args.seed, help="env seed (training range)")
    p.add_argument("--policy", default=Args.policy, help="scripted controller")
    p.add_argument("--env-id", default=Args.env_id, help="v1 id")
    p.add_argument("--out", type=Path, default=Args.out, help="PNG output")
    args = Args(**vars(p.parse_args(argv)))
    auv_follow_env.check_training_seeds([args.seed], name="--seed")
    d = record(args)
    plot(d, args)
    print(f"wrote {args.out}")
    return args.out


if __name__ == "__main__":
    main()
