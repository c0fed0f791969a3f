"""World seed ranges, in one place: training, validation (model selection) and test never share a world.

Generated worlds are deterministic in (seed, difficulty) — and family, for the goal task — so
keeping the seed ranges apart keeps the worlds apart. Training draws from :data:`TRAIN`; training's
own held-out evaluation (which picks the best checkpoint) flies :data:`VALIDATION`; reported
figures come from :data:`TEST`. ``tests/training/test_seeds.py`` holds them disjoint.
"""

from __future__ import annotations

from flightsim.envs.env import SEED_LIMIT, TRAIN_SEED_OFFSET

#: every training world's seed (LidarAvoid-v0 and LidarNav-v0 draw from here without options)
TRAIN = range(TRAIN_SEED_OFFSET, SEED_LIMIT)
#: goal task: the worlds training evaluates on to select checkpoints
VALIDATION = range(500_000, 600_000)
#: goal task: the held-out test worlds of reported figures (``avoid-train evaluate`` by default)
TEST = range(900_000, 1_000_000)
