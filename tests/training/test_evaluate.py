"""Evaluation's bookkeeping: success, near misses and summaries, on scripted episodes."""

from types import SimpleNamespace

import numpy as np
import pytest

from companion.safety.shield import SafetyShield, ShieldConfig
from training.controllers import ControllerSpec, ShieldedController
from training.episodes import EpisodeResult, WorldSpec, is_success, run_episode
from training.report import format_table, report


class ScriptedEnv:
    """Replays clearances and distances (a stand-in for the simulator in a test of pure bookkeeping)."""

    def __init__(self, clearances, step_length=0.1, collide_at=None, max_steps=None):
        self.clearances = clearances
        self.step_length = step_length
        self.collide_at = collide_at
        self.config = SimpleNamespace(max_steps=max_steps or len(clearances) - 1)
        self.unwrapped = self
        self.response_params = None  # the ideal response
        self.actions = []

    def _info(self):
        return {
            "collision": self.i == self.collide_at,
            "min_distance": self.clearances[self.i],
            "distance": self.i * self.step_length,
            "position": np.array([self.i * self.step_length, 0.0, 1.5]),
        }

    def reset(self, seed=None, options=None):
        self.i = 0
        return np.ones(360, np.float32), self._info()

    def step(self, action):
        self.actions.append(np.asarray(action))
        self.i += 1
        info = self._info()
        terminated = info["collision"]
        return (
            np.ones(360, np.float32),
            0.0,
            terminated,
            self.i >= self.config.max_steps and not terminated,
            info,
        )


class Constant:
    def reset(self, scan):
        return np.array([0.5, 0.0], np.float32)

    def act(self, scan):
        return np.array([0.5, 0.0], np.float32)


def test_near_misses_count_entries_below_half_a_metre_and_clearance_is_the_minimum():
    env = ScriptedEnv([2.0, 0.4, 0.3, 1.0, 0.45, 2.0, 0.6])
    r = run_episode(env, Constant(), {})
    assert r.near_misses == 2
    assert r.min_clearance == pytest.approx(0.3)
    assert r.steps == 6 and not r.collision
    assert len(r.trajectory) == 7 and len(env.actions) == 6


def test_a_collision_ends_the_episode_and_is_never_a_success():
    env = ScriptedEnv([2.0] * 20, step_length=10.0, collide_at=5)
    r = run_episode(env, Constant(), {})
    assert r.collision and r.steps == 5 and not r.success


@pytest.mark.parametrize(
    ("collision", "steps", "distance", "expected"),
    [
        (False, 1000, 40.0, True),
        (False, 1000, 39.9, False),  # hovering survives but does not succeed
        (False, 999, 80.0, False),  # the episode must run to max_steps
        (True, 1000, 80.0, False),
    ],
)
def test_success_needs_the_full_episode_and_40_m(collision, steps, distance, expected):
    assert is_success(collision, steps, 1000, distance, 0.1) is expected


def _result(controller, world, success, distance):
    return EpisodeResult(
        controller, world, 0, 1000, 1000, not success, distance, distance / 100, 0.4, 1, success
    )


def test_report_summarises_per_controller_and_world():
    worlds = [WorldSpec("a", seed=0), WorldSpec("b", seed=1)]
    results = [
        _result("policy", "a", True, 100.0),
        _result("policy", "b", False, 20.0),
        _result("gap_follower", "a", True, 60.0),
        _result("gap_follower", "b", True, 60.0),
    ]
    data = report(results, worlds)
    policy = data["controllers"]["policy"]
    assert policy["overall"]["success_rate"] == 0.5 and policy["overall"]["mean_distance_m"] == 60.0
    assert policy["per_world"]["b"]["collisions"] == 1
    assert data["controllers"]["gap_follower"]["overall"]["success_rate"] == 1.0
    table = format_table(data, per_world=True)
    assert "policy" in table and "ALL" in table and len(table.splitlines()) == 2 + 2 * 3


class FullAhead:
    """Asks for full forward speed and a left turn every step."""

    def reset(self, scan):
        return np.array([1.0, 1.0], np.float32)

    def act(self, scan):
        return np.array([1.0, 1.0], np.float32)


def shielded() -> ShieldedController:
    return ShieldedController(FullAhead(), SafetyShield(ShieldConfig(), max_range=10.0), 2.0, 1.5)


def test_shield_stops_forward_motion_at_a_wall_but_lets_the_vehicle_turn():
    scan = np.ones(360, np.float32)
    scan[:5] = 0.02  # 0.2 m dead ahead: inside the 0.3 m emergency-stop distance
    controller = shielded()
    cfg = ShieldConfig()
    backing = cfg.keepout_gain * (cfg.keepout_distance - 0.2) / 2.0  # the keep-out's push, in action units
    assert backing > 0.0
    for action in [controller.reset(scan)] + [controller.act(scan) for _ in range(20)]:
        assert action[0] == pytest.approx(-backing, abs=1e-3)  # no forward motion: backs off
    assert action[1] == pytest.approx(1.0)  # turning in place stays allowed, up to the full rate


def test_shield_ramps_forward_speed_at_its_acceleration_limit_in_action_units():
    clear = np.ones(360, np.float32)
    controller = shielded()
    first = controller.reset(clear)
    # 4 m/s² for one 0.1 s step = 0.4 m/s = 0.2 of the 2 m/s action scale; 4 rad/s² -> 0.4 of 1.5 rad/s
    assert first == pytest.approx([0.2, 0.4 / 1.5])
    assert controller.act(clear)[0] == pytest.approx(0.4)
    assert controller.shield.interventions["accel_limit"] == 2


def test_shield_watches_the_measured_velocity_it_is_given():
    """Sliding right at 1.1 m/s into a return 57° right of the nose: the nose sector alone would let
    full speed through; with the measured velocity the shield stops and brakes."""
    scan = np.ones(360, np.float32)
    scan[300:306] = 0.08  # 0.8 m, 55-60° right of the nose
    sliding = ShieldedController(FullAhead(), SafetyShield(ShieldConfig(), 10.0, "ardupilot"), 2.0, 1.5,
                                 velocity=lambda: np.array([0.9, -0.6]))
    blind = shielded()
    for _ in range(30):
        blind_action, action = blind.act(scan), sliding.act(scan)
    assert blind_action[0] == pytest.approx(1.0)
    assert action[0] < 0.0  # braking against the motion
    assert sliding.shield.interventions["motion_stop"] == 30


def test_shielded_rows_are_labelled_as_such():
    assert ControllerSpec("gap_follower", shield=True).label == "gap_follower+shield"
    assert ControllerSpec("policy", "p.onnx", "policy").label == "policy"


def test_every_controller_has_its_own_colour_and_the_legend_names_them_all():
    """With --shield every label ends in "+shield": each still gets its own colour."""
    from flightsim.envs.env import EnvConfig
    from training.episodes import EpisodeResult, WorldSpec
    from training.report import controller_colours, trajectory_figure

    shielded = ["policy+shield", "gap_follower+shield", "random+shield"]
    colours = controller_colours(shielded)
    assert len(set(colours.values())) == 3 and colours["policy+shield"] == "tab:blue"
    both = controller_colours(["policy", "policy+shield", "mine", "gap_follower"])
    assert len(set(both.values())) == 4 and both["policy"] == "tab:blue"

    worlds = [WorldSpec("seed-1", seed=1, difficulty=0.5), WorldSpec("seed-2", seed=2, difficulty=0.5)]
    results = [
        EpisodeResult(name, w.name, 0, 10, 10, False, 1.0, 1.0, 1.0, 0, True,
                      trajectory=[(0.0, 0.0), (1.0, 0.5 * k)])
        for w in worlds
        for k, name in enumerate(shielded)
    ]  # fmt: skip
    fig = trajectory_figure(results, worlds, EnvConfig())
    (legend,) = fig.legends
    assert sorted(t.get_text() for t in legend.get_texts()) == sorted([*shielded, "collision"])
    drawn = {line.get_color() for ax in fig.axes for line in ax.get_lines() if len(line.get_xdata()) == 2}
    assert drawn == {colours[n] for n in shielded}


class FullLeft:
    """Asks for full speed to the left (a third action component) and nothing else."""

    def reset(self, scan):
        return np.array([0.0, 0.0, 1.0], np.float32)

    def act(self, scan):
        return np.array([0.0, 0.0, 1.0], np.float32)


@pytest.mark.parametrize("wall_bin", [90, 270])
def test_the_shield_judges_a_sideways_action_and_sends_it_sideways(wall_bin: int):
    """A sideways action goes through the shield along its course: a wall 0.2 m to the left stops
    the move to the left, one to the right does not; what it lets through goes to the sideways
    setpoint, and the action handed on asks none."""
    scan = np.ones(360, np.float32)
    scan[wall_bin - 3 : wall_bin + 4] = 0.02
    sent: list[float] = []
    controller = ShieldedController(
        FullLeft(), SafetyShield(ShieldConfig(), max_range=10.0), 2.0, 1.5, lateral=sent.append,
        max_sideways_speed=1.0,
    )  # fmt: skip
    controller.reset(scan)
    for _ in range(20):
        action = controller.act(scan)
    assert action.shape == (3,) and action[2] == 0.0
    assert (sent[-1] <= 0.0) if wall_bin == 90 else (sent[-1] > 0.5)
    with pytest.raises(ValueError, match="action must have 2 values, got 3"):
        shielded_two = ShieldedController(FullLeft(), SafetyShield(ShieldConfig(), max_range=10.0), 2.0, 1.5)
        shielded_two.reset(scan)


def test_a_bad_world_file_is_skipped_with_a_warning_and_the_run_exits_2_naming_it(tmp_path, capsys):
    """Before, one bad file in ``--worlds DIR`` stopped the whole evaluation before it began."""
    import shutil
    from pathlib import Path

    from training.__main__ import main

    shutil.copy(Path(__file__).parents[2] / "flightsim" / "worlds" / "two-pillars.json", tmp_path)
    (tmp_path / "broken.json").write_text('{"name": "broken"')
    argv = ["evaluate", "--worlds", str(tmp_path), "--baselines", "gap_follower", "--workers", "1",
            "--set", "env.max_steps=10"]  # fmt: skip
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert "two-pillars" in captured.out  # the good world was flown
    err = captured.err.strip().splitlines()
    assert err[0].startswith("avoid-train: warning: skipping world ") and "broken.json" in err[0]
    assert err[-1].startswith("avoid-train: error: 1 world file(s) skipped: world ")
    assert "broken.json" in err[-1]


def test_a_directory_of_bad_world_files_only_is_one_line(tmp_path, capsys):
    from training.__main__ import main

    (tmp_path / "broken.json").write_text("[")
    assert main(["evaluate", "--worlds", str(tmp_path), "--baselines", "gap_follower"]) == 2
    assert capsys.readouterr().err.strip().endswith("none of its 1 world files loads")


def _inside(inner, outer) -> bool:
    return inner.x0 >= outer.x0 - 0.5 and inner.x1 <= outer.x1 + 0.5 and inner.y0 >= outer.y0 - 0.5 \
        and inner.y1 <= outer.y1 + 0.5


@pytest.mark.parametrize("n_worlds", [1, 3])
def test_the_legend_fits_the_png_and_covers_no_map(n_worlds):
    """Before, one row of every entry: wider than a one-world figure (cut at both edges), and over
    the panels' maps."""
    from flightsim.envs.env import EnvConfig
    from training.report import trajectory_figure

    names = ["goal_follower+shield", "path_expert+shield", "policy+shield", "predictive_expert+shield",
             "straight_line+shield"]  # fmt: skip
    worlds = [WorldSpec(f"seed-{i}", seed=i, difficulty=0.5) for i in range(n_worlds)]
    results = [
        EpisodeResult(name, w.name, 0, 10, 10, k == 0, 1.0, 1.0, 1.0, 0, True,
                      trajectory=[(0.0, 0.0), (1.0, 0.5 * k)])
        for w in worlds
        for k, name in enumerate(names)
    ]  # fmt: skip
    fig = trajectory_figure(results, worlds, EnvConfig())
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    (legend,) = fig.legends
    box = legend.get_window_extent(renderer)
    assert _inside(box, fig.bbox)
    for ax in fig.axes:
        assert not box.overlaps(ax.get_tightbbox(renderer)), ax.get_title()
