"""The hand-run fuzz targets (tests/companion/fuzz_inputs.py), a few examples each, so they do not rot.

They are property tests in their own right: a corrupted VLP-16 stream never raises and never yields a
revolution that is not one whole turn; a hostile config file is a one-line error or a config whose
floats are all finite and in range (before issue 14, ``shield.estop_distance = nan`` loaded).
"""

from __future__ import annotations

from tests.companion.fuzz_inputs import fuzz_config, fuzz_vlp16


def test_vlp16_fuzz_target() -> None:
    fuzz_vlp16(25)()


def test_config_fuzz_target(tmp_path) -> None:
    fuzz_config(40, tmp_path)()
