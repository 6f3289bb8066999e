"""Tests of the pygame leg picture: frame format, the leg where the state puts it, MPA shading."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gymnasium.error import DependencyNotInstalled

from mpa_gym.model.params import DEFAULT_PARAMS

pytest.importorskip("pygame")

from mpa_gym.envs.rendering import HIP_BLOCK, LegRenderer

P_MAX_BAR = 6.0


@pytest.fixture
def renderer():
    r = LegRenderer(DEFAULT_PARAMS, P_MAX_BAR)
    yield r
    r.close()


def world_to_pixel(r: LegRenderer, x: float, y: float) -> tuple[int, int]:
    """World (x, y) [m] -> (column, row), built from hip_pixel (rail at x = 0) and the scale."""
    col0, row = r.hip_pixel(y)
    return round(col0 + x * r.scale), row


def knee_and_femur(x_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Knee position, unit vector knee -> hip and the femur's front normal, from Fig. 2."""
    leg = DEFAULT_PARAMS.leg
    alpha = math.acos((leg.Lu**2 + x_m**2 - leg.Lo**2) / (2 * leg.Lu * x_m))
    knee = np.array([leg.Lu * math.sin(alpha), leg.Lu * math.cos(alpha)])
    uf = (np.array([0.0, x_m]) - knee) / leg.Lo
    nf = np.array([uf[1], -uf[0]])  # points forward (x > 0) while the hip is above the knee
    return knee, uf, nf


def patch_mean(frame: np.ndarray, col: int, row: int, half: int = 1) -> np.ndarray:
    return frame[row - half:row + half + 1, col - half:col + half + 1].reshape(-1, 3).mean(0)


def test_frame_format(renderer):
    frame = renderer.draw(0.8, 0.8, np.array([2.0, 1.0]), 0.0)
    assert frame.shape == (600, 480, 3)
    assert frame.dtype == np.uint8
    colours = np.unique(frame.reshape(-1, 3), axis=0)
    assert len(colours) > 10, "frame is (nearly) blank"
    assert (frame != 255).any(axis=2).mean() > 0.02


def test_scale_is_fixed_and_shows_the_leg(renderer):
    # heights 0 to 0.95 m are inside the frame, y grows downward
    (_, row_ground), (_, row_top) = renderer.hip_pixel(0.0), renderer.hip_pixel(0.95)
    assert 0 <= row_top < row_ground < renderer.height
    assert renderer.scale == pytest.approx(600.0)  # documented for the default 480 x 600 frame
    renderer.draw(0.6, 0.6, np.zeros(2), 0.0)
    assert renderer.hip_pixel(0.8) == LegRenderer(DEFAULT_PARAMS, P_MAX_BAR).hip_pixel(0.8)


def test_hip_drawn_where_the_state_says(renderer):
    rows = []
    for x in (0.78, 0.82):
        frame = renderer.draw(x, 0.7, np.array([1.0, 1.0]), 0.0)
        col, row = renderer.hip_pixel(x)
        rows.append(row)
        np.testing.assert_array_equal(frame[row - 1:row + 2, col - 1:col + 2],
                                      np.broadcast_to(HIP_BLOCK, (3, 3, 3)))
        # the other height's hip position is not covered by the block
        other = 0.82 if x == 0.78 else 0.78
        c2, r2 = renderer.hip_pixel(other)
        assert tuple(frame[r2, c2]) != HIP_BLOCK
    assert abs((rows[0] - rows[1]) - renderer.scale * 0.04) <= 1.0


@pytest.mark.parametrize("x_m", [0.6, 0.8, 0.86])
def test_knee_in_front_and_links_drawn(renderer, x_m):
    frame = renderer.draw(x_m, x_m, np.zeros(2), 0.0)
    knee, uf, _ = knee_and_femur(x_m)
    # the knee pin is dark, and so are the middles of femur and tibia
    for p in (knee, knee + 0.5 * DEFAULT_PARAMS.leg.Lo * uf, 0.5 * knee):
        col, row = world_to_pixel(renderer, *p)
        assert patch_mean(frame, col, row).max() < 120, (x_m, p)
    assert world_to_pixel(renderer, *knee)[0] > renderer.hip_pixel(x_m)[0]


def mpa_probe(renderer: LegRenderer, x_m: float, which: int) -> tuple[int, int]:
    """A pixel inside the drawn body of the extensor (0) or the flexor (1) MPA."""
    leg = DEFAULT_PARAMS.leg
    knee, uf, nf = knee_and_femur(x_m)
    if which == 0:  # along the femur's front at offset r, the body ends Lo/2 from the knee
        p = knee + (0.5 * leg.Lo - 0.04) * uf + leg.r * nf
    else:  # along the chord from the femur point at L1 towards the tibia point at L2
        a_f = knee + leg.L1 * uf
        a_t = knee - leg.L2 * knee / np.linalg.norm(knee)
        p = a_f + 0.08 * (a_t - a_f) / np.linalg.norm(a_t - a_f)
    return world_to_pixel(renderer, *p)


@pytest.mark.parametrize("which", [0, 1], ids=["extensor", "flexor"])
def test_mpa_colour_follows_pressure(renderer, which):
    x_m = DEFAULT_PARAMS.leg.x_rest
    col, row = mpa_probe(renderer, x_m, which)
    reds, greens = [], []
    for p_bar in (0.0, 0.5 * P_MAX_BAR, P_MAX_BAR, 2 * P_MAX_BAR):
        pressures = np.full(2, 1.0)
        pressures[which] = p_bar
        frame = renderer.draw(x_m, x_m, pressures, 0.0)
        rgb = patch_mean(frame, col, row)
        reds.append(rgb[0])
        greens.append(rgb[1])
    # grey at 0 bar, then redder; above p_max the picture is clipped
    np.testing.assert_allclose(reds[0], greens[0], atol=2.0)
    assert reds[0] < reds[1] < reds[2]
    assert greens[0] > greens[1] > greens[2]
    np.testing.assert_allclose([reds[3], greens[3]], [reds[2], greens[2]], atol=0.5)
    assert reds[2] - greens[2] > 150


def test_mpa_swells_with_pressure(renderer):
    x_m = DEFAULT_PARAMS.leg.x_rest

    def reddish(p_bar: float) -> int:
        """Red pixels below the text block: the extensor body (the flexor stays grey)."""
        frame = renderer.draw(x_m, x_m, np.array([p_bar, 0.0]), 0.0).astype(int)
        body = frame[renderer.height // 4:]
        return int(((body[..., 0] - body[..., 1]) > 60).sum())

    # drawn width grows by 18/13.5 = 1.33 from p_max/2 to p_max (default sizes)
    assert reddish(P_MAX_BAR) > 1.25 * reddish(0.5 * P_MAX_BAR) > 0


def test_human_mode_opens_and_closes():
    import pygame

    r = LegRenderer(DEFAULT_PARAMS, P_MAX_BAR, human=True, fps=1000)
    assert pygame.display.get_surface() is not None
    for k in range(3):
        frame = r.draw(0.8 + 0.01 * k, 0.8, np.array([1.0, 2.0]), 0.01 * k)
        assert frame.shape == (600, 480, 3)
    r.close()
    assert not pygame.display.get_init()
    r.close()  # idempotent


@pytest.mark.parametrize("bad", [np.array([1.0]), np.array([1.0, np.nan]), np.zeros(3)])
def test_bad_pressure_is_rejected(renderer, bad):
    with pytest.raises(ValueError, match="pressure_bar"):
        renderer.draw(0.8, 0.8, bad, 0.0)


def test_missing_pygame_raises_dependency_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pygame", None)
    with pytest.raises(DependencyNotInstalled, match="pip install"):
        LegRenderer(DEFAULT_PARAMS, P_MAX_BAR)


def test_import_does_not_need_pygame():
    code = "import sys, mpa_gym, mpa_gym.envs; assert 'pygame' not in sys.modules"
    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, "-c", code], cwd=root, check=True)


@pytest.mark.parametrize("env_id", ["MPALeg-v0", "MPALegResidual-v0"])
@pytest.mark.parametrize("dt_s", [0.01, 0.02, 0.004])
def test_render_fps_is_the_control_rate(env_id, dt_s):
    """One frame per control period: a video at ``render_fps`` plays at real time when the
    frame rate is 1/dt, for this instance's dt (two instances with different dt apart)."""
    import gymnasium as gym

    import mpa_gym  # noqa: F401

    env = gym.make(env_id, task={"dt_s": dt_s}, render_mode="rgb_array")
    other = gym.make(env_id, task={"dt_s": 0.05}, render_mode="rgb_array")
    assert env.metadata["render_fps"] == pytest.approx(1.0 / dt_s, rel=1e-12)
    assert other.metadata["render_fps"] == pytest.approx(20.0, rel=1e-12)
    env.reset(seed=0)
    for _ in range(7):  # the env's clock advances one frame period per step
        *_, info = env.step(np.zeros(2, dtype=np.float32))
    assert info["t_s"] * env.metadata["render_fps"] == pytest.approx(7, abs=1e-9)
    env.close()
    other.close()


def test_recorded_video_plays_at_real_time(tmp_path):
    """RecordVideo's video of a 0.5 s episode at 100 Hz lasts 0.5 s (it read render_fps), not
    the 1 s of a video declared at 50 fps. Needs moviepy (gymnasium's video writer); the
    duration it reads back is allowed one frame of rounding."""
    pytest.importorskip("moviepy")
    import gymnasium as gym
    from gymnasium.wrappers import RecordVideo
    from moviepy import VideoFileClip

    import mpa_gym  # noqa: F401

    dt_s, steps = 0.01, 50
    env = RecordVideo(gym.make("MPALegResidual-v0", task={"dt_s": dt_s, "episode_s": steps * dt_s},
                               render_mode="rgb_array"), str(tmp_path), disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, term, trunc, _ = env.step(np.zeros(2, dtype=np.float32))
        done = term or trunc
    env.close()
    (video,) = tmp_path.glob("*.mp4")
    with VideoFileClip(str(video)) as clip:
        assert clip.fps == pytest.approx(1.0 / dt_s, rel=1e-6)
        # reset's frame and one per step: steps + 1 frames at 1/dt
        assert clip.duration == pytest.approx((steps + 1) * dt_s, abs=dt_s + 1e-9)
