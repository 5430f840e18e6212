"""The shipped checkpoints' data hashes are those of the data sets scripts/train-weights.sh builds
(issue 46: checkpoints carry the data manifest's hash; the recipe rebuilds them from scratch).

The hashes come from the recipe's own `renderloop dataset` commands through
service.training.provenance.planned_data_hash, without rendering: the hash of a data set depends
on its build settings and scene seeds only. docs/models.md quotes both hashes and the one way the
shipped denoiser's data differ from the recipe's."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from models.checkpoint import DATA_KEY, RECIPE_KEY, read_checkpoint
from models.pretrained import DENOISER_FILE, ERROR_PREDICTOR_FILE, SHIPPED_WEIGHTS_DIR
from service.cli import build_parser
from service.dataset.build import DatasetSettings
from service.training.provenance import planned_data_hash
from tests.test_train_recipe import recipe_commands

REPO = Path(__file__).resolve().parents[1]


def dataset_settings(argv: list[str]) -> tuple[str, DatasetSettings]:
    """A recipe's `renderloop dataset ...` line → its output folder and the settings it builds with."""
    args = build_parser().parse_args(argv)
    return str(args.out), DatasetSettings(scenes=args.scenes, size=args.size, frames=args.frames, seed=args.seed,
                                          split=args.split, reference_spp=args.reference_spp,
                                          loop_branch=args.loop_branch, layout=args.layout)


@pytest.fixture(scope="module")
def recipe() -> tuple[dict[str, DatasetSettings], dict[str, list[str]]]:
    """The full recipe's data sets by folder, and each recipe name's last training run's --data folders
    (the run that writes the shipped file)."""
    builds, trained_on = {}, {}
    for argv in recipe_commands():
        if argv[:2] == ["renderloop", "dataset"]:
            out, settings = dataset_settings(argv[1:])
            builds[out] = settings
        elif argv[:2] == ["renderloop", "train"]:
            args = build_parser().parse_args(argv[1:])
            trained_on[args.recipe] = [str(root) for root in args.data]
    return builds, trained_on


def shipped_extra(name: str) -> dict:
    return read_checkpoint(SHIPPED_WEIGHTS_DIR / name)["extra"]


def test_the_shipped_error_network_trained_on_the_recipes_data_sets(recipe):
    builds, trained_on = recipe
    extra = shipped_extra(ERROR_PREDICTOR_FILE)
    assert extra[DATA_KEY] == planned_data_hash(builds[root] for root in trained_on[extra[RECIPE_KEY]])


def test_the_shipped_denoisers_data_differ_from_the_recipes_only_as_its_model_card_says(recipe):
    """docs/models.md: its shaded rooms were built with --loop-branch (extra items the denoiser does
    not read), which the hash includes; the recipe builds them without."""
    builds, trained_on = recipe
    extra = shipped_extra(DENOISER_FILE)
    roots = trained_on[extra[RECIPE_KEY]]
    as_recipe = [builds[root] for root in roots]
    as_shipped = [dataclasses.replace(s, loop_branch=True) if s.layout == "shaded" else s for s in as_recipe]
    assert planned_data_hash(as_shipped) == extra[DATA_KEY] != planned_data_hash(as_recipe)


def test_the_model_card_quotes_each_shipped_networks_recipe_and_data_hash():
    card = (REPO / "docs" / "models.md").read_text(encoding="utf-8")
    for name in (DENOISER_FILE, ERROR_PREDICTOR_FILE):
        extra = shipped_extra(name)
        assert extra[RECIPE_KEY] in card and extra[DATA_KEY] in card, name
