"""A symmetrised policy file answers a world and its mirror image alike (training.symmetrise),
on real ONNX Runtime, and the companion flies it as any exported policy."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from companion.app import policy_spec
from companion.common.errors import UserError
from companion.config import CompanionConfig
from companion.guidance.policy import OnnxPolicy
from training.__main__ import main
from training.symmetrise import SYMMETRISED_KEY, mirror_of, symmetrise_onnx

SHIPPED = Path(__file__).resolve().parents[2] / "models" / "policy.onnx"
#: the shipped file's metadata, and the mirror of the frames it reads
METADATA = {p.key: p.value for p in onnx.load(str(SHIPPED)).metadata_props}
MIRROR = mirror_of(METADATA)


def actions(path: Path, obs: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(None, {"observation": obs})[0]


@pytest.fixture(scope="module")
def symmetrised(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sym") / "policy-sym.onnx"
    assert symmetrise_onnx(SHIPPED, out) <= 1e-5
    return out


def observations(n: int = 64) -> np.ndarray:
    """Every element drawn from 0.1-1 (scans, goal, velocity and drift alike): not a flight, but
    every input the mirror moves, with no element at the 0 a sign flip leaves alone."""
    return np.random.default_rng(3).uniform(0.1, 1.0, (n, MIRROR.index.size)).astype(np.float32)


def test_the_symmetrised_policy_is_exactly_symmetric_and_the_shipped_one_is_not(symmetrised: Path) -> None:
    obs = observations()
    mirrored = MIRROR.observations(obs).astype(np.float32)
    original_gap = np.abs(actions(SHIPPED, obs) - MIRROR.actions(actions(SHIPPED, mirrored))).max()
    assert original_gap > 1e-2  # the network learnt the symmetry only roughly
    answer = actions(symmetrised, obs)
    np.testing.assert_allclose(answer, MIRROR.actions(actions(symmetrised, mirrored)), atol=1e-6)


def test_its_action_is_the_mean_of_the_action_and_the_mirrored_action(symmetrised: Path) -> None:
    obs = observations()
    expected = 0.5 * (actions(SHIPPED, obs) + MIRROR.actions(actions(SHIPPED, MIRROR.observations(obs))))
    np.testing.assert_allclose(actions(symmetrised, obs), expected, atol=1e-6)


def test_it_keeps_the_metadata_says_so_and_the_companion_loads_it(symmetrised: Path) -> None:
    after = {p.key: p.value for p in onnx.load(str(symmetrised)).metadata_props}
    assert SYMMETRISED_KEY not in METADATA
    assert {k: v for k, v in after.items() if k != SYMMETRISED_KEY} == METADATA
    assert SYMMETRISED_KEY in after
    policy = OnnxPolicy(symmetrised, policy_spec(CompanionConfig()))
    action = policy.act(observations(1)[0])
    assert action.shape == (3,) and np.all(np.abs(action) <= 1.0)  # the shipped model flies sideways


def test_bad_input_is_one_line_and_exit_2(
    tmp_path: Path, symmetrised: Path, capsys: pytest.CaptureFixture
) -> None:
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    cases = [
        (["--model", str(tmp_path / "missing.onnx")], "model file not found"),
        (["--model", str(junk)], "is not an ONNX model"),
        (["--model", str(symmetrised)], "is symmetrised already"),
    ]
    for args, message in cases:
        assert main(["symmetrise", *args, "--out", str(tmp_path / "out.onnx")]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1
    same = tmp_path / "same.onnx"
    shutil.copy(SHIPPED, same)
    assert main(["symmetrise", "--model", str(same), "--out", str(same)]) == 2
    assert "--out must differ" in capsys.readouterr().err


def test_a_model_whose_metadata_disagrees_with_its_config_is_refused(tmp_path: Path) -> None:
    model = onnx.load(str(SHIPPED))
    for entry in model.metadata_props:
        if entry.key == "lidar_avoid.obs_layout":
            entry.value = "scan360"
    bad = tmp_path / "bad.onnx"
    onnx.save(model, str(bad))
    with pytest.raises(UserError, match=r"the model's config feeds .* its metadata names scan360"):
        symmetrise_onnx(bad, tmp_path / "out.onnx")
