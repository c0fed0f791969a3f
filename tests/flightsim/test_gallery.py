"""World pictures: waypoints drawn numbered (the active one highlighted), and `avoid-sim worlds`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flightsim.__main__ import main
from flightsim.worlds.render import render_rgb
from flightsim.worlds.world import Box, World, load_world

WORLD = World(
    "wp", (10.0, 6.0), 3.0, (Box((0.0, 0.0, 0.3), (2.0, 2.0, 0.6)), Box((2.5, 1.0, 1.5), (3.0, 0.3, 0.3))),
    (-4.0, 0.0, 1.5), 0.0, ((3.0, -2.0, 1.5), (-3.0, 2.0, 1.5)),
)  # fmt: skip


def _fraction(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 12) -> float:
    return float((np.abs(img.astype(int) - rgb).max(axis=-1) <= tol).mean())


GREEN, ORANGE = (0x2A, 0x9D, 0x3F), (0xE0, 0x8A, 0x00)
LOW, BEAM = (0xE3, 0xE3, 0xE3), (0xB0, 0xB0, 0xB0)


def test_waypoints_are_drawn_and_the_active_one_stands_out() -> None:
    plain = render_rgb(WORLD, np.zeros((0, 3)))
    assert _fraction(plain, GREEN) > 0.0003 and _fraction(plain, ORANGE) == 0.0
    active = render_rgb(WORLD, np.zeros((0, 3)), active_waypoint=1)
    assert _fraction(active, ORANGE) > 0.0003
    none = render_rgb(World("e", (10.0, 6.0), 3.0, (), (-4.0, 0.0, 1.5), 0.0), np.zeros((0, 3)))
    assert _fraction(none, GREEN) == 0.0


def test_low_and_floating_obstacles_are_drawn_apart() -> None:
    img = render_rgb(WORLD, np.zeros((0, 3)))
    assert _fraction(img, LOW, tol=4) > 0.005  # the 0.6 m box: flown over
    assert _fraction(img, BEAM, tol=6) > 0.0005  # the beam at 1.35-1.65 m, hatched


def test_gallery_and_save(tmp_path, capsys) -> None:
    png = tmp_path / "g.png"
    assert main(["worlds", "--gallery", str(png), "--save", str(tmp_path / "w"), "--family", "gaps",
                 "--family", "traps", "--seed", "3", "--difficulty", "1"]) == 0  # fmt: skip
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = sorted((tmp_path / "w").glob("*.json"))
    assert [p.name for p in saved] == ["gaps-3-d1.00.json", "traps-3-d1.00.json"]
    assert load_world(saved[0]).waypoints == tuple(
        tuple(w) for w in json.loads(saved[0].read_text())["waypoints"]
    )
    assert "gaps-3-d1.00" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--gallery", "x.png", "--difficulty", "2"], "--difficulty must be in [0, 1]"),
        (["--gallery", "x.png", "--seed", "-1"], "--seed must be non-negative"),
        (["--gallery", "x.png", "--radius", "0"], "--radius must be in"),
        ([], "nothing to do"),
        (["--gallery", "/nonexistent-dir/x.png", "--family", "gaps"], "--gallery /nonexistent-dir/x.png"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(args: list[str], words: str, capsys) -> None:
    assert main(["worlds", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err
