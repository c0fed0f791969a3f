"""``avoid-train symmetrise``: a policy file that flies the same in a world and in its mirror image.

The task is left-right symmetric (:mod:`training.mirror`), and the students are fitted to mirrored
labels too, but a network is symmetric only as far as it learnt to be. The symmetrised file answers
the mean of the policy's action and the mirrored action it gives the mirrored observation:
``(π(o) + M_a π(M_o o)) / 2``. That is exactly symmetric, and a mean of two predictions per member,
as an ensemble is a mean over members.

It wraps the exported ONNX graph rather than the torch modules, so it applies to any exported file
(also one whose checkpoints are gone): the graph runs twice, on the observation and on its mirror
(a ``Gather`` and a ``Mul``), and the two actions are averaged. The metadata is kept (the companion
checks the layout as for any other file) and says it was symmetrised.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

from companion.common.errors import UserError
from training.export import INPUT_NAME, OUTPUT_NAME, PARITY_TOLERANCE
from training.mirror import Mirror, mirror_for

#: metadata key marking a symmetrised file (its value: what the action is)
SYMMETRISED_KEY = "lidar_avoid.symmetrised"
_FIRST, _SECOND = "direct/", "mirrored/"


def mirror_of(metadata: dict[str, str]) -> Mirror:
    """The mirror of the stacked frames an exported policy reads, from its metadata (its training
    config gives the layout; the layout it names must agree).

    :raises UserError: the metadata lacks the config or the layout, or they disagree
    """
    from training.config import config_from_dict
    from training.export import policy_spec_for

    try:
        config = config_from_dict(json.loads(metadata["lidar_avoid.config"]))
        named = metadata["lidar_avoid.obs_layout"]
    except (KeyError, ValueError, TypeError) as exc:
        raise UserError(f"the model's metadata does not say what it reads: {exc}") from None
    spec = policy_spec_for(config)
    if spec.layout.name != named:
        raise UserError(f"the model's config feeds {spec.layout.name}, its metadata names {named}")
    return mirror_for(spec.layout, spec.stack, getattr(config.env_config(), "sideways", False))


def symmetrise_onnx(src: Path, out: Path) -> float:
    """Write the symmetrised ``src`` to ``out`` and return the largest deviation of its actions from
    ``(π(o) + M_a π(M_o o)) / 2`` computed with ``src`` on random observations (raise if too large).

    :raises UserError: ``src`` is not a readable exported policy, or is symmetrised already
    """
    import onnx
    from onnx import compose, helper, numpy_helper

    try:
        model = onnx.load(str(src))
    except Exception as exc:  # protobuf's decode errors have no common base
        raise UserError(f"{src} is not an ONNX model: {exc}") from None
    metadata = {p.key: p.value for p in model.metadata_props}
    if SYMMETRISED_KEY in metadata:
        raise UserError(f"{src} is symmetrised already")
    mirror = mirror_of(metadata)
    # the direct copy reads the observation itself; the mirrored one reads the Gather and Mul below
    direct = compose.add_prefix(model, _FIRST, rename_inputs=False)
    mirrored = compose.add_prefix(model, _SECOND)
    nodes = [
        helper.make_node("Gather", [INPUT_NAME, "mirror_index"], ["mirror_gathered"], axis=1),
        helper.make_node("Mul", ["mirror_gathered", "mirror_signs"], [_SECOND + INPUT_NAME]),
        *direct.graph.node,
        *mirrored.graph.node,
        helper.make_node("Mul", [_SECOND + OUTPUT_NAME, "mirror_action_signs"], ["mirrored_back"]),
        helper.make_node("Add", [_FIRST + OUTPUT_NAME, "mirrored_back"], ["action_sum"]),
        helper.make_node("Mul", ["action_sum", "half"], [OUTPUT_NAME]),
    ]
    constants = [
        numpy_helper.from_array(mirror.index.astype(np.int64), "mirror_index"),
        numpy_helper.from_array(mirror.signs.astype(np.float32), "mirror_signs"),
        numpy_helper.from_array(mirror.action_signs.astype(np.float32), "mirror_action_signs"),
        numpy_helper.from_array(np.array(0.5, dtype=np.float32), "half"),
    ]
    graph = helper.make_graph(
        nodes, "symmetrised", list(model.graph.input), list(model.graph.output),
        [*direct.graph.initializer, *mirrored.graph.initializer, *constants],
    )  # fmt: skip
    proto = helper.make_model(graph, opset_imports=model.opset_import, producer_name=model.producer_name)
    proto.ir_version = model.ir_version
    for key, value in (metadata | {SYMMETRISED_KEY: "mean of the action and the mirrored action"}).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.doc_string = f"{model.doc_string}, symmetrised across the nose"
    onnx.checker.check_model(proto, full_check=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(proto, str(out))
    return _parity(src, out, mirror)


def _parity(src: Path, out: Path, mirror: Mirror, samples: int = 256) -> float:
    """Largest deviation of ``out``'s actions from the symmetrised mean computed with ``src``."""
    import onnxruntime as ort

    source, wrapped = (ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]) for p in (src, out))
    obs = np.random.default_rng(0).uniform(0.0, 1.0, (samples, mirror.index.size)).astype(np.float32)
    mirrored = mirror.observations(obs).astype(np.float32)
    direct, back = (source.run(None, {INPUT_NAME: o})[0] for o in (obs, mirrored))
    expected = 0.5 * (direct + mirror.actions(back))
    diff = float(np.abs(wrapped.run(None, {INPUT_NAME: obs})[0] - expected).max())
    if diff > PARITY_TOLERANCE:
        raise RuntimeError(f"symmetrised parity failed: max abs diff {diff:.3g} > {PARITY_TOLERANCE:g}")
    return diff


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, required=True, help="exported policy (.onnx) to symmetrise")
    parser.add_argument("--out", type=Path, required=True, help="ONNX file to write")


def command(args: argparse.Namespace) -> int:
    if not args.model.is_file():
        raise UserError(f"model file not found: {args.model}")
    if args.out.resolve() == args.model.resolve():
        raise UserError(f"--out must differ from --model ({args.out})")
    diff = symmetrise_onnx(args.model, args.out)
    print(f"symmetrised {args.model} into {args.out}: max abs diff vs the mirrored mean {diff:.3g}")
    print(f"sha256 {hashlib.sha256(args.out.read_bytes()).hexdigest()}  {args.out}")
    return 0
