"""Record a video of a controller following its target (gymnasium's RecordVideo; needs moviepy).

    python examples/record_video.py                          # a full 60 s Hard episode -> ./videos
    python examples/record_video.py --steps 100 --out /tmp/v # 5 s only

The frames are ``env.render()`` with ``render_mode="rgb_array"``: 600 x 600 pixels, 6 m across,
the target red, the true reference green, the follower blue and, on the v1 ids, the fixes the
follower received (orange; the newest purple, with its age).
"""

from __future__ import annotations

import argparse
import os

import gymnasium as gym
from gymnasium.wrappers import RecordVideo

import auv_follow_env  # noqa: F401  (registers the ids)
from controllers import make_controller


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="AUVFollow-Hard-v1")
    parser.add_argument("--controller", default="PROPOSED_KF_DOB")
    parser.add_argument("--steps", type=int, default=1200, help="control steps to record (1200 = 60 s)")
    parser.add_argument("--out", default="videos", help="folder for the mp4 files")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps {args.steps}: must be at least 1")
    env = RecordVideo(gym.make(args.env_id, render_mode="rgb_array"), args.out,
                      episode_trigger=lambda episode: episode == 0, disable_logger=True)
    policy = make_controller(args.controller, env.unwrapped.task_spec)
    obs, info = env.reset(seed=12)                       # a training seed
    for _ in range(args.steps):
        action, _ = policy.predict(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    env.close()                                          # writes the episode recorded so far
    print("wrote", ", ".join(sorted(os.listdir(args.out))), "in", args.out)


if __name__ == "__main__":
    main()
