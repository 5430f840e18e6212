"""scripts/train-weights.sh: the shipped networks' recipe from scratch stays runnable as the CLI
changes, and its smoke mode runs every step end to end on tiny data."""
import os
import shlex
import subprocess
from pathlib import Path

import pytest

from models.checkpoint import DATA_KEY, RECIPE_KEY, load_checkpoint
from models.denoiser import DenoiserConfig
from service.cli import build_parser
from service.train_command import train_config

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "scripts" / "train-weights.sh"


def recipe_commands(*argv: str) -> list[list[str]]:
    result = subprocess.run(["bash", str(RECIPE), *argv], cwd=ROOT, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "DRY_RUN": "1"})
    assert result.returncode == 0, result.stderr
    return [shlex.split(line[2:]) for line in result.stdout.splitlines() if line.startswith("+ ")]


@pytest.mark.parametrize("mode", [(), ("--smoke",)])
def test_every_recipe_command_parses_and_every_training_config_validates(mode):
    renderloop = [argv[1:] for argv in recipe_commands(*mode) if argv[0] == "renderloop"]
    verbs = [argv[0] for argv in renderloop]
    assert verbs[:6] == ["dataset", "dataset", "train", "train", "train", "train"]
    stages = []
    for argv in renderloop:
        if argv[0] == "bench":
            continue   # bench parses its own arguments (tests/bench)
        args = build_parser().parse_args(argv)   # a renamed or removed flag fails here
        if argv[0] == "train":
            config = train_config(args)
            config.validate()
            stages.append(config.stage)
            assert not config.temporal and config.recipe in ("kpcn-single-frame-oidn", "error-spp-disagreement")
    assert stages == ["single", "multiscale", "gate", "lambda", "error", "error"]
    assert ("bench" in verbs) == (not mode)   # the calibration on scenes/val: the full recipe only


def test_no_recipe_command_names_a_machine_path():
    for argv in recipe_commands():
        assert not any(arg.startswith(("/", "~")) for arg in argv), argv


def test_an_unknown_argument_is_refused_with_a_message():
    result = subprocess.run(["bash", str(RECIPE), "--fast"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "unknown argument" in result.stderr


@pytest.mark.slow
def test_the_smoke_run_builds_loadable_networks_of_the_shipped_configuration(tmp_path):
    env = {**os.environ, "DATA": str(tmp_path / "data"), "OUT": str(tmp_path / "out"),
           "PATH": f"{ROOT / '.venv' / 'bin'}:{os.environ['PATH']}"}
    result = subprocess.run(["bash", str(RECIPE), "--smoke"], cwd=ROOT, capture_output=True, text=True,
                            timeout=1800, env=env)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
    final = tmp_path / "out" / "final"
    denoiser = load_checkpoint(final / "denoiser.pt", expected_kind="denoiser")
    error_net = load_checkpoint(final / "error_predictor.pt", expected_kind="error_predictor")
    assert denoiser.config == DenoiserConfig()
    assert denoiser.checkpoint_extra[RECIPE_KEY] == "kpcn-single-frame-oidn"
    assert error_net.checkpoint_extra[RECIPE_KEY] == "error-spp-disagreement"
    assert denoiser.checkpoint_extra[DATA_KEY] != error_net.checkpoint_extra[DATA_KEY]   # two data sets each
