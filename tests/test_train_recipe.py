"""scripts/train-weights.sh: the shipped denoiser's recipe stays runnable as the CLI changes."""
import os
import shlex
import subprocess
from pathlib import Path

import pytest

from service.cli import build_parser
from service.train_command import train_config

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "scripts" / "train-weights.sh"


def recipe_commands(profile: str) -> list[list[str]]:
    result = subprocess.run(["bash", str(RECIPE)], cwd=ROOT, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "DRY_RUN": "1", "PROFILE": profile})
    assert result.returncode == 0, result.stderr
    return [shlex.split(line[2:]) for line in result.stdout.splitlines() if line.startswith("+ ")]


@pytest.mark.parametrize("profile", ["cpu", "gpu"])
def test_every_recipe_command_parses_and_every_training_config_validates(profile):
    commands = recipe_commands(profile)
    renderloop = [argv[1:] for argv in commands if argv[0] == "renderloop"]
    assert [argv[0] for argv in renderloop] == ["dataset"] * 3 + ["train"] * 2
    for argv in renderloop:
        args = build_parser().parse_args(argv)   # a renamed or removed flag fails here
        if argv[0] == "train":
            config = train_config(args)
            config.validate()
            assert config.keep_settings and config.candidate_features   # the shipped network's settings
    scenes = [int(argv[argv.index("--scenes") + 1]) for argv in renderloop if argv[0] == "dataset"]
    assert scenes == ([400, 40, 60] if profile == "cpu" else [4000, 400, 600])


def test_an_unknown_profile_is_refused_with_a_message():
    result = subprocess.run(["bash", str(RECIPE)], cwd=ROOT, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "DRY_RUN": "1", "PROFILE": "tpu"})
    assert result.returncode == 2 and "PROFILE must be cpu or gpu" in result.stderr
