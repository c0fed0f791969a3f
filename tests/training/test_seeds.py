"""Training, validation and test worlds never share a seed (flightsim/envs/seeds.py is the one place)."""

from itertools import combinations

from flightsim.envs import seeds
from flightsim.envs.env import TRAIN_SEED_OFFSET
from training.config import EvalConfig, load_train_config


def test_seed_ranges_are_disjoint_and_training_is_what_the_envs_draw_from():
    ranges = {"train": seeds.TRAIN, "validation": seeds.VALIDATION, "test": seeds.TEST}
    for (a, ra), (b, rb) in combinations(ranges.items(), 2):
        assert max(ra.start, rb.start) >= min(ra.stop, rb.stop), f"{a} and {b} overlap"
    assert seeds.TRAIN.start == TRAIN_SEED_OFFSET


def test_the_nav_config_validates_on_validation_seeds_only():
    config = load_train_config("training/configs/nav.toml")
    first = config.eval.first_seed
    assert first in seeds.VALIDATION and first + config.eval.n_worlds - 1 in seeds.VALIDATION
    assert EvalConfig().first_seed not in seeds.TEST
