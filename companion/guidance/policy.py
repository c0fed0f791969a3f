"""The learned policy, run with ONNX Runtime, refusing any model that was not trained for this setup.

The training export writes :data:`METADATA_KEYS` into the ONNX file's ``metadata_props`` (through
:func:`policy_metadata`, so both sides agree by construction). At load time the companion checks
every one against its own configuration: a model trained on another range, stack depth, bin
order or speed scaling would fly the vehicle wrongly without any error, so it must not start.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from companion.common.errors import UserError
from companion.common.userfile import read_user_bytes
from companion.perception.observation import ObservationLayout
from companion.perception.scan import BIN_CONVENTION

log = logging.getLogger(__name__)

FORMAT_VERSION = "1"
PREFIX = "lidar_avoid."
METADATA_KEYS: dict[str, str] = {
    PREFIX + "format": "metadata format version, " + FORMAT_VERSION,
    PREFIX + "obs_size": "input length: stack × frame size (perception.observation.ObservationLayout)",
    PREFIX + "stack": "scans per observation, oldest first",
    PREFIX + "n_bins": "bins per scan",
    PREFIX + "max_range": "metres a scan value of 1.0 stands for",
    PREFIX + "bin_convention": "bin order, companion.perception.scan.BIN_CONVENTION",
    PREFIX + "max_speed": "m/s that action a0 = 1 stands for",
    PREFIX + "max_yaw_rate": "rad/s that action a1 = 1 stands for (counter-clockwise positive)",
    PREFIX + "max_sideways_speed": "m/s that action a2 = 1 stands for (to the left); 0: no a2",
    PREFIX + "config": "the training configuration, JSON (informational)",
    PREFIX + "obs_layout": "one frame's layout, companion.perception.observation.ObservationLayout.name",
}
#: a model exported before ``obs_layout`` existed was trained on scans only
LEGACY_LAYOUT = ObservationLayout().name
#: keys a model exported before them lacks, and what such a model was trained with
LEGACY_VALUES = {PREFIX + "obs_layout": LEGACY_LAYOUT, PREFIX + "max_sideways_speed": "0.0"}

#: A policy is a small MLP (under 1 MB); a model file larger than this is not one.
MAX_MODEL_BYTES = 256 << 20

# Execution providers in order of preference; whichever of them this onnxruntime build has is used.
PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")

# The companion config key each spec field comes from, for error messages.
_CONFIG_KEYS = {
    "stack": "policy.stack",
    "n_bins": "scan bins",
    "max_range": "scan.max_range",
    "bin_convention": "scan bin convention",
    "max_speed": "policy.max_speed",
    "max_yaw_rate": "policy.max_yaw_rate",
    "max_sideways_speed": "policy.max_sideways_speed",
    "obs_layout": "observation layout",
}


@dataclass(frozen=True)
class PolicySpec:
    """What the companion feeds the policy and how it reads the action; the model must agree.

    :param stack: scans per observation
    :param n_bins: bins per scan
    :param max_range: metres that a scan value of 1.0 stands for
    :param bin_convention: bin order (:data:`companion.perception.scan.BIN_CONVENTION`)
    :param max_speed: m/s that a0 = 1 stands for
    :param max_yaw_rate: rad/s that a1 = 1 stands for
    :param max_sideways_speed: m/s that a2 = 1 stands for, a speed to the left (0: the action has
        no a2, as a model trained without ``env.sideways``)
    :param layout: one frame of the observation (scan only, or scan + goal + velocity)
    """

    stack: int = 4
    n_bins: int = 360
    max_range: float = 10.0
    bin_convention: str = BIN_CONVENTION
    max_speed: float = 2.0
    max_yaw_rate: float = 1.5
    max_sideways_speed: float = 0.0
    layout: ObservationLayout = ObservationLayout()

    def __post_init__(self) -> None:
        if self.layout.n_bins != self.n_bins:
            raise ValueError(f"layout {self.layout.name} does not have {self.n_bins} bins")

    @property
    def obs_size(self) -> int:
        return self.stack * self.layout.frame_size

    @property
    def action_size(self) -> int:
        """Values per action: forward and yaw rate, and a sideways speed when the model has one."""
        return 3 if self.max_sideways_speed > 0.0 else 2


class InferenceFault(Exception):
    """Inference raised or produced a non-finite action; the supervisor holds, the process carries on."""


def policy_metadata(spec: PolicySpec, config_json: str) -> dict[str, str]:
    """The ONNX ``metadata_props`` the training export writes for a model trained under ``spec``.

    :param spec: what the policy was trained on
    :param config_json: the training configuration as JSON
    """
    json.loads(config_json)  # must be valid JSON: raises ValueError otherwise
    return {
        PREFIX + "format": FORMAT_VERSION,
        PREFIX + "obs_size": str(spec.obs_size),
        PREFIX + "stack": str(spec.stack),
        PREFIX + "n_bins": str(spec.n_bins),
        PREFIX + "max_range": repr(float(spec.max_range)),
        PREFIX + "bin_convention": spec.bin_convention,
        PREFIX + "max_speed": repr(float(spec.max_speed)),
        PREFIX + "max_yaw_rate": repr(float(spec.max_yaw_rate)),
        PREFIX + "max_sideways_speed": repr(float(spec.max_sideways_speed)),
        PREFIX + "config": config_json,
        PREFIX + "obs_layout": spec.layout.name,
    }


def read_model_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of the ONNX model at ``path``, unchecked: what a tool that flies any
    exported model (``avoid-sim fly``, ``avoid-train evaluate``) reads to configure itself for it.

    :raises UserError: unreadable, not an ONNX model, or metadata that is not UTF-8
    """
    path = Path(path)
    model = read_user_bytes(path, "policy model", MAX_MODEL_BYTES)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        session = ort.InferenceSession(model, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UserError(f"policy model {path} is not a loadable ONNX model: {detail}") from None
    try:
        return dict(session.get_modelmeta().custom_metadata_map)
    except UnicodeDecodeError as exc:
        raise UserError(
            f"policy model {path}: metadata is not UTF-8 text ({exc.reason} at byte {exc.start})"
        ) from None


def select_providers(requested: Sequence[str] | None = None) -> list[str]:
    """The execution providers to ask for, in preference order, limited to those available.

    :param requested: providers to try instead of :data:`PREFERRED_PROVIDERS`
    """
    available = set(ort.get_available_providers())
    wanted = list(requested) if requested is not None else list(PREFERRED_PROVIDERS)
    chosen = [p for p in wanted if p in available]
    if not chosen:
        raise UserError(
            f"none of the ONNX Runtime providers {', '.join(wanted)} is available "
            f"(available: {', '.join(sorted(available))})"
        )
    return chosen


def provider_options(
    providers: Sequence[str], trt_cache_dir: str | None
) -> list[str | tuple[str, dict[str, str]]]:
    """Providers for ONNX Runtime, with TensorRT's engine cache pointed at ``trt_cache_dir``.

    Building a TensorRT engine takes minutes on a Jetson; with the cache (the service's
    StateDirectory) only the first start after a model change pays for it.
    """
    if not trt_cache_dir:
        return list(providers)
    options = {"trt_engine_cache_enable": "True", "trt_engine_cache_path": trt_cache_dir}
    return [(p, options) if p == "TensorrtExecutionProvider" else p for p in providers]


class OnnxPolicy:
    """A policy network loaded from an ``.onnx`` file and checked against ``spec``.

    :param path: the model file (from ``avoid-train export``)
    :param spec: what the companion will feed it; the model's metadata must match
    :param providers: execution providers to try (default TensorRT → CUDA → CPU, as available)
    :param trt_cache_dir: where TensorRT keeps its built engines, in one directory per model hash
        (``None``: no cache)
    :param sha256: the file's expected SHA-256 (hex; ``None`` or empty: not checked)
    :raises UserError: unreadable or not ONNX, not the expected hash, wrong input/output shape,
        metadata missing, not UTF-8 or not matching ``spec``; the message names both values
    """

    def __init__(
        self,
        path: str | Path,
        spec: PolicySpec,
        providers: Sequence[str] | None = None,
        trt_cache_dir: str | None = None,
        sha256: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.spec = spec
        model = read_user_bytes(self.path, "policy model", MAX_MODEL_BYTES)
        #: SHA-256 of the model file, hex: logged at start-up, compared with ``policy.sha256``.
        self.sha256 = hashlib.sha256(model).hexdigest()
        if sha256 and sha256.lower() != self.sha256:
            raise UserError(
                f"policy model {self.path}: sha256 {self.sha256} is not the configured policy.sha256 "
                f"{sha256.lower()} (a different or corrupted file)"
            )
        options = ort.SessionOptions()
        # One small MLP per scan: a single thread has the lowest, steadiest latency and leaves the
        # other cores to the lidar and MAVLink.
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(
                model,  # the bytes hashed above, not the path: the file may change in between
                sess_options=options,
                providers=provider_options(select_providers(providers), self._engine_cache(trt_cache_dir)),
            )
        except UserError:
            raise
        except Exception as exc:
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise UserError(f"policy model {self.path} is not a loadable ONNX model: {detail}") from None
        self.providers: list[str] = list(self._session.get_providers())
        self._check_layout()
        self._check_io()
        self._check_metadata()
        self._input_name = self._session.get_inputs()[0].name
        self._output_names = [self._session.get_outputs()[0].name]
        self._run_options = ort.RunOptions()
        self._run_options.log_severity_level = 4  # a failed run is reported once, as InferenceFault
        log.info("policy %s (sha256 %s) loaded, ONNX Runtime providers in use: %s", self.path, self.sha256,
                 ", ".join(self.providers))

    def _engine_cache(self, trt_cache_dir: str | None) -> str | None:
        """This model's own directory under ``trt_cache_dir``, named by its hash.

        ONNX Runtime keys TensorRT engines on the model's path, or its graph when loaded from bytes,
        never on its weights: a retrained model of the same shape would run the old engine.
        """
        if not trt_cache_dir:
            return None
        directory = Path(trt_cache_dir) / self.sha256[:16]
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"policy.trt_cache_dir: cannot create {directory}: {exc.strerror}") from None
        return str(directory)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """One action for one stacked observation.

        :param obs: ``(stack × frame size,)`` float32, oldest frame first
        :return: ``(2,)`` float32 in ``[-1, 1]``: a0 forward, a1 yaw rate (counter-clockwise positive);
            ``(3,)`` when the spec has a sideways speed: a2 to the left
        :raises InferenceFault: inference raised, or its output was not ``action_size`` finite numbers
        """
        x = np.asarray(obs, dtype=np.float32).reshape(1, -1)
        if x.shape[1] != self.spec.obs_size:
            raise ValueError(f"observation has {x.shape[1]} values, the policy takes {self.spec.obs_size}")
        try:
            out = self._session.run(self._output_names, {self._input_name: x}, self._run_options)[0]
        except Exception as exc:
            raise InferenceFault(f"inference raised {type(exc).__name__}: {exc}") from exc
        action = np.asarray(out, dtype=np.float32).reshape(-1)
        size = self.spec.action_size
        if action.shape[0] != size:
            raise InferenceFault(f"inference returned {action.shape[0]} values, expected {size}")
        if not np.isfinite(action).all():
            raise InferenceFault(f"inference returned a non-finite action {action.tolist()}")
        return np.clip(action, -1.0, 1.0)

    def _check_io(self) -> None:
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1:
            raise UserError(f"policy model {self.path} has {len(inputs)} inputs, expected 1")
        inp = inputs[0]
        want = f"(1, {self.spec.obs_size}) float32"
        if inp.type != "tensor(float)":
            raise UserError(f"policy model input is {inp.type}, expected {want}")
        if len(inp.shape) != 2 or not _batch_dim_ok(inp.shape[0]) or inp.shape[1] != self.spec.obs_size:
            raise UserError(
                f"model input shape {_shape(inp.shape)} does not match config {want} "
                f"(stack {self.spec.stack} × {self.spec.layout.frame_size}: {self.spec.layout.name})"
            )
        out, size = outputs[0], self.spec.action_size
        want = f"(1, {size}) float32"
        if out.type != "tensor(float)" or len(out.shape) != 2 or not _batch_dim_ok(out.shape[0]):
            raise UserError(f"model output {_shape(out.shape)} {out.type} is not {want}")
        if out.shape[-1] != size:
            configured = self.spec.max_sideways_speed
            raise UserError(
                f"model output {_shape(out.shape)} does not match config {want} (policy.max_sideways_speed "
                f"{configured:g}{_sideways_hint(self._metadata(), configured)})"
            )

    def _metadata(self) -> dict[str, str]:
        """The model's metadata map (one line, not a traceback, when a file breaks its UTF-8)."""
        try:
            return dict(self._session.get_modelmeta().custom_metadata_map)
        except UnicodeDecodeError as exc:  # protobuf strings are UTF-8 by contract; a file can break it
            raise UserError(
                f"policy model {self.path}: metadata is not UTF-8 text ({exc.reason} at byte {exc.start})"
            ) from None

    def _check_layout(self) -> None:
        """Before the shapes: a layout mismatch is named as such, not as an input size."""
        meta = {**LEGACY_VALUES, **self._metadata()}
        try:
            self._compare("obs_layout", meta, self.spec.layout.name, _CONFIG_KEYS["obs_layout"])
        except UserError as exc:
            scan_only = meta[PREFIX + "obs_layout"] == ObservationLayout(n_bins=self.spec.n_bins).name
            if scan_only and self.spec.layout.goal:  # the default config is the goal layout
                raise UserError(f'{exc} (a scan-only model: set policy.observation = "scan")') from None
            for part in ("drift", "command", "firmware", "movers"):
                in_model = f"+{part}(" in meta[PREFIX + "obs_layout"]
                if self.spec.layout.goal and in_model != getattr(self.spec.layout, part):
                    hint = (
                        f"set policy.{part} = true"
                        if in_model
                        else f"the model has none: policy.{part} = false"
                    )
                    raise UserError(f"{exc} ({part} features: {hint})") from None
            raise

    def _check_metadata(self) -> None:
        meta = {**LEGACY_VALUES, **self._metadata()}
        missing = [key for key in METADATA_KEYS if key not in meta]
        if missing:
            raise UserError(
                f"policy model {self.path} lacks metadata {', '.join(missing)} "
                "(export it with `avoid-train export`)"
            )
        if meta[PREFIX + "format"] != FORMAT_VERSION:
            raise UserError(
                f"model metadata format {meta[PREFIX + 'format']!r} is not the supported {FORMAT_VERSION!r}"
            )
        try:
            json.loads(meta[PREFIX + "config"])
        except ValueError:
            raise UserError(f"model metadata {PREFIX}config is not valid JSON") from None
        spec = self.spec
        self._compare("obs_size", meta, spec.obs_size, "observation size")
        for name in ("stack", "n_bins", "max_range", "bin_convention", "max_speed", "max_yaw_rate",
                     "max_sideways_speed"):
            self._compare(name, meta, getattr(spec, name), _CONFIG_KEYS[name])

    def _compare(self, name: str, meta: dict[str, str], expected: object, config_key: str) -> None:
        raw = meta[PREFIX + name]
        if isinstance(expected, str):
            same = raw == expected
        else:
            try:
                value = float(raw)
            except ValueError:
                raise UserError(f"model metadata {PREFIX}{name} = {raw!r} is not a number") from None
            same = math.isclose(value, float(expected), rel_tol=1e-6, abs_tol=1e-9)
        if not same:
            raise UserError(f"model {name} {raw} does not match config {config_key} {expected}")


def declared_sideways_speed(meta: Mapping[str, str]) -> float | None:
    """The sideways speed a model's metadata declares, m/s (absent, as in older models: 0, no a2),
    or None when the value is not a finite, non-negative number.

    :param meta: the model's custom metadata
    """
    key = PREFIX + "max_sideways_speed"
    try:
        speed = float(meta.get(key, LEGACY_VALUES[key]))
    except ValueError:
        return None
    return speed if math.isfinite(speed) and speed >= 0.0 else None


def _sideways_hint(meta: dict[str, str], configured: float) -> str:
    """The setting the model's metadata asks for, when it names one other than ``configured``."""
    speed = declared_sideways_speed(meta)
    if speed is None or math.isclose(speed, configured):
        return ""
    return f"; set policy.max_sideways_speed = {speed:g}, as the model's metadata says"


def _batch_dim_ok(dim: object) -> bool:
    """A batch dimension of 1 or symbolic (``None``/a name) accepts a single observation."""
    return dim == 1 or dim is None or isinstance(dim, str)


def _shape(shape: Sequence[object]) -> str:
    return "(" + ", ".join("N" if not isinstance(d, int) else str(d) for d in shape) + ")"
