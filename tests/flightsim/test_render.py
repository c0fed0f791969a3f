"""Top-down pictures: the environment's rgb_array frames and the reusable PNG plotter."""

from __future__ import annotations

import numpy as np
import pytest

from flightsim.envs.env import EnvConfig, LidarAvoidEnv
from flightsim.worlds.render import draw_top_down, plot_worlds, render_rgb
from flightsim.worlds.world import Box, Cylinder, World, generate_world

WORLD = World(
    "render", (10.0, 6.0), 3.0,
    (Box((2.0, 1.0, 1.5), (1.0, 2.0, 3.0), 30.0), Cylinder((-2.0, -1.0), 0.6, 3.0)),
    (-4.0, 0.0, 1.5), 0.0,
)  # fmt: skip


def _reddish(img: np.ndarray) -> float:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return float(((r - g > 60) & (r - b > 60)).mean())


def _colour_fraction(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 12) -> float:
    return float((np.abs(img.astype(int) - rgb).max(axis=-1) <= tol).mean())


def test_render_rgb_draws_walls_obstacles_trajectory_scan_and_vehicle() -> None:
    scan = np.ones(360, np.float32)
    scan[:30] = 0.4  # returns ahead-left
    traj = np.array([[-4.0, 0.0, 1.5], [-3.0, 0.2, 1.5], [-2.0, 1.0, 1.5]])
    img = render_rgb(WORLD, traj, scan=scan, pose=(traj[-1], 0.3), title="t")
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[1] == 720 and 300 < img.shape[0] < 720  # follows the room's aspect
    assert _colour_fraction(img, (0x30, 0x30, 0x30)) > 0.005  # walls
    assert _colour_fraction(img, (0x8C, 0x8C, 0x8C)) > 0.005  # obstacles
    assert _colour_fraction(img, (0x1F, 0x77, 0xB4), tol=30) > 0.0005  # trajectory
    assert _reddish(img) > 0.001  # rays with a return
    assert _colour_fraction(img, (0x1F, 0x5F, 0xBF), tol=20) > 0.0002  # the vehicle disc
    without_scan = render_rgb(WORLD, traj, pose=(traj[-1], 0.3), title="t")
    assert _reddish(without_scan) < 0.0001


def test_collision_is_drawn_red() -> None:
    img = render_rgb(WORLD, np.zeros((0, 3)), pose=(np.array([0.0, 0.0, 1.5]), 0.0), collided=True)
    assert _colour_fraction(img, (0xD6, 0x27, 0x28), tol=20) > 0.0005


def test_env_rgb_array_frames() -> None:
    env = LidarAvoidEnv(EnvConfig(max_steps=10), render_mode="rgb_array")
    env.reset(seed=2, options={"world": WORLD})
    first = env.render()
    for _ in range(5):
        env.step(np.array([1.0, 0.0], np.float32))
    later = env.render()
    assert first.shape == later.shape and first.dtype == np.uint8
    assert not np.array_equal(first, later)  # the vehicle moved and the trajectory grew
    assert LidarAvoidEnv(EnvConfig()).render() is None  # no render_mode: nothing
    with pytest.raises(ValueError, match="render_mode"):
        LidarAvoidEnv(render_mode="human")


def test_plot_worlds_writes_a_png(tmp_path) -> None:
    trajectories = [np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 1.5]]), np.array([[0.0, 0.0], [-1.0, 2.0]])]
    panels = [(WORLD, trajectories, "two flights"), (generate_world(1, 1.0), [], "generated, d=1")]
    path = plot_worlds(tmp_path / "worlds.png", panels, columns=2)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    with pytest.raises(ValueError, match="at least one panel"):
        plot_worlds(tmp_path / "none.png", [])


def test_draw_top_down_on_given_axes() -> None:
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    assert draw_top_down(WORLD, np.array([[0.0, 0.0], [1.0, 0.0]]), ax=ax, title="x") is ax
    assert ax.get_title() == "x"
    assert ax.get_xlim() == pytest.approx((-5.5, 5.5))


def test_labelled_trajectories_get_a_legend_that_names_everything_drawn() -> None:
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    paths = [np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[1.0, 0.0], [2.0, 1.0]])]
    pose = (np.array([2.0, 1.0, 1.5]), 0.0)
    draw_top_down(WORLD, paths, ax=ax, pose=pose, collided=True, labels=("take-off", "companion"))
    names = [t.get_text() for t in ax.get_legend().get_texts()]
    assert names == ["start (arrow: heading)", "take-off", "companion", "vehicle", "collision"]
    plain = Figure().add_subplot()
    draw_top_down(WORLD, paths, ax=plain)
    assert plain.get_legend() is None  # panels of a grid share one legend of their own
