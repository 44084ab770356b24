"""Rendering as the env docstring documents it: rgb_array frames, the fixes received on v1 drawn
where they were received, no audio in human mode, RecordVideo, and episodes unchanged by rendering."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env import layout
from auv_follow_env.rendering import NEWEST_FIX_COLOUR

ROOT = Path(__file__).resolve().parents[1]
EASY = "AUVFollow-Easy-v1"
# the documented frame: 600 x 600 px showing 6 m, centred on the follower/true-reference midpoint, y up
SIZE, PX_PER_M = 600, 100.0


@pytest.mark.parametrize("env_id, dt, fps", [("AUVFollow-S4-v0", None, 20), (EASY, None, 20), (EASY, 0.1, 10)])
def test_rgb_array_frames_have_the_documented_shape_dtype_and_fps(env_id, dt, fps):
    kw = {} if dt is None else {"dt": dt}
    env = gym.make(env_id, render_mode="rgb_array", **kw)
    assert env.metadata["render_fps"] == fps  # round(1 / dt)
    env.reset(seed=0)
    first = env.render()
    env.step(np.zeros(3, np.float32))
    frame = env.render()
    for f in (first, frame):
        assert isinstance(f, np.ndarray) and f.shape == (SIZE, SIZE, 3) and f.dtype == np.uint8
    env.close()


def _pixel(x: float, y: float, cx: float, cy: float) -> tuple[int, int]:
    """(row, column) of world point (x, y) in the documented frame centred on (cx, cy)."""
    return int(SIZE / 2 - (y - cy) * PX_PER_M), int(SIZE / 2 + (x - cx) * PX_PER_M)


def test_v1_frame_marks_the_newest_received_fix_where_it_was_received():
    """The newest fix's position is recovered from the observation alone (target_dx/dy in the
    follower's body frame, plus the follower's pose from info); the frame must carry the marker's
    colour around that pixel, and the same scene drawn without fixes must not."""
    env = gym.make(EASY, render_mode="rgb_array")
    obs, info = env.reset(seed=1000001)
    ix = layout.OBS_INDEX_V1
    checked = 0
    for _ in range(200):
        obs, _, terminated, truncated, info = env.step(np.zeros(3, np.float32))
        assert not (terminated or truncated)
        if obs[ix["new_packet"]] != 1.0 or obs[ix["has_packet"]] != 1.0:
            continue
        xf, yf, psi = info["follower_pose"]
        dx, dy = float(obs[ix["target_dx"]]), float(obs[ix["target_dy"]])
        xw = xf + math.cos(psi) * dx - math.sin(psi) * dy  # body frame -> world
        yw = yf + math.sin(psi) * dx + math.cos(psi) * dy
        xr, yr = info["true_reference"][:2]
        row, col = _pixel(xw, yw, 0.5 * (xf + xr), 0.5 * (yf + yr))
        if not (160 <= row < SIZE - 60 and 10 <= col < SIZE - 60):  # off the frame or under the text
            continue
        frame = env.render()
        region = frame[row - 2:row + 3, col - 2:col + 3].reshape(-1, 3)
        assert (region == NEWEST_FIX_COLOUR).all(), f"no newest-fix marker at ({row}, {col}): {region.tolist()}"
        u = env.unwrapped
        bare = u._renderer.draw(list(u._trails), info["time"], info["tracking_error"], [])
        assert not (bare[row - 2:row + 3, col - 2:col + 3].reshape(-1, 3) == NEWEST_FIX_COLOUR).all(axis=1).any()
        assert (frame != bare).any(axis=2)[row - 2:row + 3, col - 2:col + 3].all()
        checked += 1
        if checked == 3:
            break
    assert checked == 3, "too few fixes inside the frame to check"
    env.close()


@pytest.mark.parametrize("mode", ["rgb_array", "human"])
def test_rendering_changes_no_episode(mode, monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    runs = []
    for render_mode in (None, mode):
        env = gym.make("AUVFollow-Hard-v1", render_mode=render_mode)
        obs, _ = env.reset(seed=3000000)
        rng = np.random.default_rng(0)
        out = [obs]
        for _ in range(60):
            obs, rew, *_ = env.step(rng.uniform(-1, 1, 3))
            if render_mode == "rgb_array":
                env.render()
            out += [obs, np.array([rew])]
        env.close()
        runs.append(np.concatenate([a.ravel().astype(np.float64) for a in out]))
    np.testing.assert_array_equal(runs[0], runs[1])


_HUMAN = """
import numpy as np, gymnasium as gym, auv_follow_env, pygame
env = gym.make("AUVFollow-Easy-v1", render_mode="human")
env.reset(seed=0)
for _ in range(3):
    env.step(np.zeros(3, np.float32))
env.render()
print("mixer", pygame.mixer.get_init(), "display", pygame.display.get_init())
env.close()
"""


@pytest.mark.parametrize("audio", ["dummy", None])
def test_human_mode_never_starts_pygame_audio(audio):
    """With a working (dummy) audio driver, pygame.init() would start the mixer; without one it
    prints ALSA errors on a headless machine. Human mode must do neither."""
    env = {k: v for k, v in os.environ.items() if k != "SDL_AUDIODRIVER"}
    env["SDL_VIDEODRIVER"] = "dummy"
    if audio:
        env["SDL_AUDIODRIVER"] = audio
    res = subprocess.run([sys.executable, "-c", _HUMAN], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    assert "mixer None display True" in res.stdout
    assert "ALSA" not in res.stderr


def test_human_mode_without_a_usable_display_is_one_clear_error():
    code = ("import gymnasium as gym, auv_follow_env\n"
            "e = gym.make('AUVFollow-S4-v0', render_mode='human')\n"
            "try:\n    e.reset(seed=0)\nexcept RuntimeError as x:\n    print(x)")
    env = {**os.environ, "SDL_VIDEODRIVER": "no-such-driver"}
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "render_mode='human' cannot open a window" in res.stdout and "SDL_VIDEODRIVER=dummy" in res.stdout
    assert "'no-such-driver'" in res.stdout


def test_v1_frame_without_any_fix_says_so_and_marks_nothing():
    """Every packet lost (loss_prob=1): the follower never hears the target, so no marker may be
    drawn (the newest-fix colour appears only in the legend, above row 160)."""
    env = gym.make("AUVFollow-v1", render_mode="rgb_array", loss_prob=1.0)
    obs, _ = env.reset(seed=0)
    for _ in range(40):
        obs, *_ = env.step(np.zeros(3, np.float32))
    assert obs[layout.OBS_INDEX_V1["has_packet"]] == 0.0
    frame = env.render()
    assert not (frame[160:] == NEWEST_FIX_COLOUR).all(axis=2).any()
    assert (frame[:160] == NEWEST_FIX_COLOUR).all(axis=2).any()  # the legend entry
    env.close()


def test_record_video_writes_a_playable_file(tmp_path):
    pytest.importorskip("moviepy")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(gym.make(EASY, render_mode="rgb_array", episode_s=1.0, steady_start_s=0.5),
                      str(tmp_path / "videos"), episode_trigger=lambda e: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(np.zeros(3, np.float32))
        done = terminated or truncated
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    from moviepy import VideoFileClip

    with VideoFileClip(str(videos[0])) as clip:
        assert list(clip.size) == [SIZE, SIZE]
        assert clip.fps == 20
