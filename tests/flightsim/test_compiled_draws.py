"""The compiled draws are numpy's: the same numbers, and the generators left in the same state."""

from __future__ import annotations

import numpy as np
import pytest

from flightsim.envs.compiled_draws import draw, state_address


def _draw_both(seeds: list[int], n_normal: list[int], uniform_shape: tuple[int, ...]):
    """The same draws through numpy and compiled, from generators seeded alike."""
    by_numpy = [np.random.default_rng(s) for s in seeds]
    compiled = [np.random.default_rng(s) for s in seeds]
    counts = np.array(n_normal, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    normals = np.empty(offsets[-1])
    uniforms = np.empty((len(seeds), *uniform_shape))
    addresses = np.array([state_address(g) for g in compiled], dtype=np.int64)
    draw(addresses, counts, normals, offsets[:-1], uniforms)
    for i, g in enumerate(by_numpy):
        expected_normals = g.standard_normal(counts[i])
        expected_uniforms = g.random(uniform_shape)
        mine = normals[offsets[i] : offsets[i + 1]]
        assert np.array_equal(mine.view(np.uint64), expected_normals.view(np.uint64))
        assert np.array_equal(uniforms[i].view(np.uint64), expected_uniforms.view(np.uint64))
        assert compiled[i].bit_generator.state == g.bit_generator.state
        assert compiled[i].normal(size=3).tolist() == g.normal(size=3).tolist()  # numpy carries on alike
    return normals


def test_normals_and_uniforms_are_numpys_bit_for_bit() -> None:
    """Two million normals exercise every branch of the ziggurat: the strips' rejection test and
    the tail beyond r = 3.654 (about 500 of them here)."""
    normals = _draw_both([0, 1, 2**40 + 7, 12345], [500_000, 700_000, 1, 800_000], (360, 16))
    assert (np.abs(normals) > 3.6541528853610088).sum() > 100  # the tail was drawn


def test_nothing_to_draw_leaves_the_generators_alone() -> None:
    _draw_both([3, 4], [0, 0], (0, 0))
    _draw_both([5, 6], [0, 10], (2, 3))


@pytest.mark.parametrize("bit_generator", [np.random.PCG64DXSM, np.random.MT19937, np.random.Philox])
def test_other_bit_generators_are_not_covered(bit_generator) -> None:
    assert state_address(np.random.Generator(bit_generator(1))) is None
    assert state_address(np.random.default_rng(1)) is not None
