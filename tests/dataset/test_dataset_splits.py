import pytest

from service.dataset.splits import HELDOUT_SEED_BASE, SPLIT_BASES, SPLIT_SIZE, TRAIN_SEED_BASE, scene_seeds



def split_of(scene_seed: int) -> str:
    return next(split for split, base in SPLIT_BASES.items() if base <= scene_seed < base + SPLIT_SIZE)


def test_train_and_heldout_seeds_are_disjoint_whatever_the_dataset_seed():
    train = {s for k in range(5) for s in scene_seeds("train", 200, k)}
    heldout = {s for k in range(5) for s in scene_seeds("heldout", 200, k)}
    assert not train & heldout
    assert all(TRAIN_SEED_BASE <= s < TRAIN_SEED_BASE + SPLIT_SIZE for s in train)
    assert all(HELDOUT_SEED_BASE <= s < HELDOUT_SEED_BASE + SPLIT_SIZE for s in heldout)
    assert {split_of(s) for s in train} == {"train"} and {split_of(s) for s in heldout} == {"heldout"}


def test_seeds_are_distinct_reproducible_and_prefix_stable():
    seeds = scene_seeds("train", 50, 3)
    assert len(set(seeds)) == 50
    assert seeds == scene_seeds("train", 50, 3)
    assert scene_seeds("train", 80, 3)[:50] == seeds  # more scenes extend a data set
    assert scene_seeds("train", 50, 4) != seeds


@pytest.mark.parametrize("split, n, seed", [("test", 1, 0), ("train", -1, 0), ("train", 1, -1)])
def test_bad_arguments_raise(split, n, seed):
    with pytest.raises(ValueError):
        scene_seeds(split, n, seed)
