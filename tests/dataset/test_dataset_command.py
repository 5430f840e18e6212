import argparse
from pathlib import Path

import pytest

from service.dataset.command import add_parser, run
from service.train_command import add_parser as add_train_parser
from service.train_command import run_train, train_config
from service.training.config import TrainConfig


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="renderloop")
    add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def test_parser_reads_every_option(tmp_path):
    args = parse(["dataset", "-o", str(tmp_path), "--scenes", "3", "--size", "32", "--frames", "5",
                  "--seed", "7", "--split", "heldout", "--reference-spp", "256"])
    assert (args.scenes, args.size, args.frames, args.seed, args.split, args.reference_spp) == (3, 32, 5, 7, "heldout", 256)
    assert args.handler is run and args.layout == "mixed"
    assert parse(["dataset", "-o", str(tmp_path), "--layout", "window"]).layout == "window"


@pytest.mark.parametrize("open_layout", ["room", "ground"])
def test_the_open_layouts_come_only_in_the_default_mix(tmp_path, open_layout, capsys):
    """A data set of rooms open at the front alone, or of ground alone, is no recipe step's: those
    layouts are what each seed of the default `mixed` draws (issue 46)."""
    with pytest.raises(SystemExit):
        parse(["dataset", "-o", str(tmp_path), "--layout", open_layout])
    assert "invalid choice" in capsys.readouterr().err


def test_train_reads_several_data_sets_and_trains_on_all_of_them():
    parser = argparse.ArgumentParser(prog="renderloop")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    config = train_config(parser.parse_args(["train", "--data", "a", "--data", "b", "--stage", "error"]))
    assert config.data_roots == (Path("a"), Path("b"))
    assert TrainConfig(data=Path("a")).data_roots == (Path("a"),)


def parse_train(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="renderloop")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["train", *argv])


@pytest.mark.parametrize("argv, message", [
    (["--stage", "lambda"], "--stage lambda trains part of a denoiser: name it with --init"),
    (["--stage", "gate", "--init", "d.pt", "--temporal"], "leave out --temporal"),
    (["--stage", "temporal"], "add --temporal"),
    (["--stage", "single", "--recipe", "my recipe"], "--recipe is a short name"),
])
def test_train_refuses_what_it_cannot_train_in_one_line(capsys, argv, message):
    assert run_train(parse_train(["--data", "d", *argv])) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("renderloop train: error:") and message in err and "\n" not in err


def test_train_has_only_the_recipes_flags():
    parser = argparse.ArgumentParser(prog="renderloop")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    train = parser._subparsers._group_actions[0].choices["train"]
    flags = {option for action in train._actions for option in action.option_strings if option.startswith("--")}
    assert flags == {"--help", "--data", "--stage", "--out", "--init", "--steps", "--batch", "--crop", "--lr",
                     "--val-every", "--seed", "--temporal", "--error-levels", "--recipe", "--resume", "--device",
                     "--quiet"}


@pytest.mark.parametrize("option, value", [("--scenes", "0"), ("--size", "2"), ("--frames", "-1"),
                                           ("--reference-spp", "0"), ("--seed", "-3")])
def test_bad_values_fail_with_one_line(tmp_path, capsys, option, value):
    assert run(parse(["dataset", "-o", str(tmp_path / "d"), option, value, "--quiet"])) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("renderloop dataset: error:") and option in err and "\n" not in err


def test_out_must_be_a_folder(tmp_path, capsys):
    file = tmp_path / "file"
    file.write_text("x")
    assert run(parse(["dataset", "-o", str(file), "--quiet"])) == 2
    assert "not a folder" in capsys.readouterr().err


def test_command_resumes_a_finished_data_set(still_dataset, capsys):
    args = parse(["dataset", "-o", str(still_dataset), "--scenes", "2", "--size", "16", "--frames", "1",
                  "--split", "heldout", "--reference-spp", "64", "--quiet"])
    assert run(args) == 0
    assert "manifest.json" in capsys.readouterr().out
