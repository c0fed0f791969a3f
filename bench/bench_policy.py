"""Figure: the companion's inference time per scan (``OnnxPolicy.act``, ONNX Runtime on one CPU
thread, as the service runs it without a GPU), against the 0.1 s control period and, measured in the
same run on the same observations, against a reference model (e.g. the previous shipped policy).

Prints the median and p99 wall time per call of each model, then the ratios: the model's median over
the reference's, and the model's p99 as a share of the control period. The machine's speed and load
move the absolute times several-fold, the ratios much less. The load average is printed.

    python bench/bench_policy.py [--model models/policy.onnx] [--reference OLD.onnx] [--calls 2000]

Both models must take the observation the companion's default configuration builds; the
reference may have the two-part action of the models before the sideways one (its metadata says).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.app import policy_spec  # noqa: E402
from companion.common.errors import UserError  # noqa: E402
from companion.config import CompanionConfig  # noqa: E402
from companion.guidance.policy import PREFIX, OnnxPolicy, PolicySpec, declared_sideways_speed  # noqa: E402

#: s between scans: the companion acts once per scan at 10 Hz
CONTROL_PERIOD_S = 0.1
#: what the companion feeds the policy under its default configuration
SPEC = policy_spec(CompanionConfig())


def reference_spec(path: Path) -> PolicySpec:
    """:data:`SPEC` with the action width ``path``'s metadata gives (absent: two parts)."""
    try:
        meta = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).get_modelmeta()
    except Exception as exc:  # ONNX Runtime raises its own classes for an unreadable model
        raise UserError(f"{path}: not a readable ONNX model ({exc})") from None
    sideways = declared_sideways_speed(meta.custom_metadata_map)
    if sideways is None:
        raise UserError(f"{path}: metadata {PREFIX}max_sideways_speed is not a speed")
    return dataclasses.replace(SPEC, max_sideways_speed=sideways)


def time_calls(policy: OnnxPolicy, observations: np.ndarray) -> np.ndarray:
    """Wall time of each ``act`` over ``observations``, seconds (after a warm-up of 50 calls)."""
    for obs in observations[:50]:
        policy.act(obs)
    times = np.empty(len(observations))
    for i, obs in enumerate(observations):
        start = time.perf_counter()
        policy.act(obs)
        times[i] = time.perf_counter() - start
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "policy.onnx")
    parser.add_argument("--reference", type=Path, help="a second model timed on the same observations")
    parser.add_argument("--calls", type=int, default=2000)
    args = parser.parse_args()
    try:
        policies = {"model": OnnxPolicy(args.model, SPEC, providers=["CPUExecutionProvider"])}
        if args.reference:
            policies["reference"] = OnnxPolicy(args.reference, reference_spec(args.reference),
                                               providers=["CPUExecutionProvider"])
    except UserError as exc:
        print(f"bench_policy: error: {exc}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    observations = rng.uniform(0.0, 1.0, (args.calls, SPEC.obs_size)).astype(np.float32)
    medians = {}
    for name, policy in policies.items():
        times = time_calls(policy, observations)
        medians[name] = float(np.median(times))
        p99 = float(np.percentile(times, 99))
        print(f"{name} {policy.path}: median {medians[name] * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us per scan"
              f" ({p99 / CONTROL_PERIOD_S:.2%} of the {CONTROL_PERIOD_S:g} s control period)")  # fmt: skip
    if "reference" in medians:
        print(f"model / reference median: {medians['model'] / medians['reference']:.2f}x")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
