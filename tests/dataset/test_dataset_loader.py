import pytest
import torch
from torch.utils.data import DataLoader

from service.dataset.build import DatasetError
from service.dataset.loader import DenoiserDataset, collate_samples
from service.training.config import TrainConfig
from service.training.trainer import _datasets


def test_windows_are_finite_crops_with_motion(sequence_dataset):
    ds = DenoiserDataset(sequence_dataset, radius=1, crop=8, seed=3)
    assert len(ds) == 2 * 6  # 2 scenes × one full 3-frame window × 6 input levels
    sample = ds[0]
    noisy = sample.noisy
    assert noisy.color.shape == (3, 3, 8, 8) and noisy.depth.shape == (3, 1, 8, 8)
    assert noisy.motion.shape == (3, 2, 8, 8) and sample.reference.shape == (3, 3, 8, 8)
    for tensor in (noisy.color, noisy.variance, noisy.albedo, noisy.normal, noisy.depth, noisy.motion, sample.reference):
        assert tensor.dtype == torch.float32 and torch.isfinite(tensor).all()
    assert sample.centre == 1


def test_crops_are_seeded_and_change_with_the_epoch(sequence_dataset):
    a = DenoiserDataset(sequence_dataset, radius=1, crop=8, seed=3)
    b = DenoiserDataset(sequence_dataset, radius=1, crop=8, seed=3)
    assert [a[i].key for i in range(len(a))] == [b[i].key for i in range(len(b))]
    assert torch.equal(a[5].noisy.color, b[5].noisy.color)
    b.set_epoch(1)
    assert [a[i].key for i in range(len(a))] != [b[i].key for i in range(len(b))]


def test_batches_collate_per_window_position(sequence_dataset):
    ds = DenoiserDataset(sequence_dataset, radius=1, crop=8, levels=("spp16", "adaptive32"))
    batch = next(iter(DataLoader(ds, batch_size=4, collate_fn=collate_samples)))
    assert len(batch.frames) == 3 and batch.centre == 1
    assert batch.frames[0].color.shape == (4, 3, 8, 8) and batch.frames[2].motion.shape == (4, 2, 8, 8)
    assert batch.references[1].shape == (4, 3, 8, 8)


def test_single_frames_have_no_motion_and_full_frames_work(still_dataset):
    ds = DenoiserDataset(still_dataset, split="heldout", crop=None)
    sample = ds[0]
    assert sample.noisy.motion is None and sample.noisy.color.shape == (1, 3, 16, 16)


@pytest.mark.parametrize("kwargs, message", [
    ({"split": "heldout", "radius": 1}, "needs 3"), ({"split": "heldout", "crop": 32}, "does not fit"),
    ({"split": "train"}, "no 'train' split"), ({"split": "heldout", "levels": ("spp8",)}, "unknown input levels"),
])
def test_bad_requests_say_what_is_wrong(still_dataset, kwargs, message):
    with pytest.raises(DatasetError, match=message):
        DenoiserDataset(still_dataset, **kwargs)


def test_a_data_set_over_several_folders_serves_the_items_of_all_of_them(still_dataset, sequence_dataset):
    one = DenoiserDataset(still_dataset, split="heldout", crop=None)
    both = DenoiserDataset([still_dataset, still_dataset], split="heldout", crop=None)
    assert len(both) == 2 * len(one) and both.items[: len(one)] == one.items
    with pytest.raises(DatasetError, match="no 'heldout' split"):
        DenoiserDataset([still_dataset, sequence_dataset], split="heldout")


def test_validation_scenes_are_held_back_from_training(sequence_dataset):
    config = TrainConfig(data=sequence_dataset, crop=16)
    train, val = _datasets(config, radius=0)
    train_scenes, val_scenes = {i.scene for i in train.items}, {i.scene for i in val.items}
    assert train_scenes and val_scenes and not train_scenes & val_scenes
    assert val.crop is None and train.crop == 16
