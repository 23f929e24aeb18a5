"""The command line's one vocabulary: the same flag means the same thing in every command, and each
renamed flag keeps working for one version under its old name, with one line on stderr saying the new
one. The parser is walked directly (``explorer.cli.build_parser``): nothing is trained or measured."""

from __future__ import annotations

import argparse
import json
import re

import pytest

from explorer.cli import build_parser

OLD_NAMES = ("--limit", "--train-steps", "--max-steps", "--input")
TRAINS = ("train", "supernet train", "search")
DEPLOYMENT_RESOLUTION = ("search", "profile", "enumerate", "export", "evaluate", "data inspect")
RUNS_ONNXRUNTIME = ("profile", "run", "curve", "calibrate")
FRAME_COUNTS = ("evaluate", "data inspect", "curve")


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command, its parser) for every command and subcommand."""
    if path:
        yield " ".join(path), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, path + (name,))


COMMANDS = dict(_commands(build_parser()))


def _visible(command: str) -> dict[str, argparse.Action]:
    """The options --help shows, by every name they have."""
    return {name: a for a in COMMANDS[command]._actions if a.help != argparse.SUPPRESS
            for name in a.option_strings}


def test_build_parser_returns_the_whole_parser_without_parsing():
    parser = build_parser()
    assert isinstance(parser, argparse.ArgumentParser) and parser.prog == "explorer"
    assert {"train", "supernet train", "search", "profile", "export", "run", "curve", "calibrate"} <= set(COMMANDS)


def test_no_old_name_is_shown():
    for command in COMMANDS:
        shown = set(_visible(command)) & set(OLD_NAMES)
        assert not shown, (command, shown)


def test_no_help_text_mentions_an_old_name():
    old = re.compile(r"--(limit|train-steps|max-steps)\b|--input(?!-size)\b")
    for command in COMMANDS:
        for name, action in _visible(command).items():
            assert not old.search(action.help or ""), (command, name, action.help)


@pytest.mark.parametrize("command", TRAINS)
def test_commands_that_train_take_train_size(command):
    assert "--train-size" in _visible(command)


@pytest.mark.parametrize("command", ("train", "supernet train"))
def test_input_size_is_not_a_training_resolution(command):
    assert "--input-size" not in _visible(command)


@pytest.mark.parametrize("command", DEPLOYMENT_RESOLUTION)
def test_deployment_resolution_is_input_size(command):
    assert "--input-size" in _visible(command)


def test_steps_name_what_they_train():
    for command in ("train", "supernet train"):
        assert "--steps" in _visible(command), command
    search = _visible("search")
    assert {"--proxy-steps", "--supernet-steps", "--finalist-steps"} <= set(search) and "--steps" not in search
    assert "--stop-after-steps" in _visible("supernet train")


@pytest.mark.parametrize("command", FRAME_COUNTS)
def test_frame_counts_are_frames(command):
    assert "--frames" in _visible(command)


def test_export_counts_frames_per_use():
    assert {"--calibration-frames", "--eval-frames"} <= set(_visible("export"))


@pytest.mark.parametrize("command", RUNS_ONNXRUNTIME)
def test_provider_wherever_onnxruntime_runs(command):
    provider = _visible(command).get("--provider")
    assert provider is not None and provider.default == "CPUExecutionProvider"


def test_every_out_says_file_or_folder():
    outs = {command: _visible(command)["--out"] for command in COMMANDS if "--out" in _visible(command)}
    assert len(outs) >= 6
    for command, action in outs.items():
        assert re.search(r"\b(file|folder)\b", action.help), (command, action.help)
        assert action.required or re.search(r"\b(default|needed)\b", action.help), (command, action.help)


# command, arguments it needs, old name, new name, value, destination, parsed value
DEPRECATED = [
    ("train", ["cand.yaml"], "--input-size", "--train-size", "32x32", "train_size", (32, 32)),
    ("train", ["cand.yaml"], "--input", "--train-size", "32x32", "train_size", (32, 32)),
    ("supernet train", [], "--input-size", "--train-size", "32x32", "train_size", (32, 32)),
    ("supernet train", [], "--input", "--train-size", "32x32", "train_size", (32, 32)),
    ("supernet train", [], "--max-steps", "--stop-after-steps", "3", "stop_after_steps", 3),
    ("search", [], "--train-steps", "--proxy-steps", "7", "proxy_steps", 7),
    ("search", [], "--input", "--input-size", "96x96", "input_size", (96, 96)),
    ("evaluate", ["c.pt"], "--limit", "--frames", "5", "frames", 5),
    ("evaluate", ["c.pt"], "--input", "--input-size", "96x96", "input_size", (96, 96)),
    ("data inspect", [], "--limit", "--frames", "5", "frames", 5),
    ("data inspect", [], "--input", "--input-size", "96x96", "input_size", (96, 96)),
    ("profile", ["paper"], "--input", "--input-size", "96x96", "input_size", (96, 96)),
    ("enumerate", [], "--input", "--input-size", "96x96", "input_size", (96, 96)),
    ("export", ["--out", "m"], "--input", "--input-size", "96x96", "input_size", (96, 96)),
]


@pytest.mark.parametrize("command, needed, old, new, value, dest, parsed", DEPRECATED,
                         ids=[f"{c[0]} {c[2]}" for c in DEPRECATED])
def test_an_old_name_stores_into_the_new_one_with_one_line(capsys, command, needed, old, new, value, dest,
                                                           parsed):
    args = build_parser().parse_args([*command.split(), *needed, old, value])
    assert getattr(args, dest) == parsed
    assert capsys.readouterr().err == (f"explorer: {old} is deprecated, use {new} "
                                       "(the old name goes in the next version)\n")
    again = build_parser().parse_args([*command.split(), *needed, new, value])
    assert getattr(again, dest) == parsed and capsys.readouterr().err == ""


def test_an_old_name_leaves_the_default_alone(capsys):
    args = build_parser().parse_args(["supernet", "train"])
    assert args.train_size is None and args.stop_after_steps is None    # None: the --recipe's size
    assert build_parser().parse_args(["search"]).proxy_steps == 150
    assert capsys.readouterr().err == ""


def test_an_old_name_through_the_whole_command(run_cli):
    """The line comes before the command's own output, which stays clean for --json."""
    code, out, err = run_cli("profile", "paper", "--input", "64x64", "--json")
    assert code == 0 and json.loads(out)["input_size"] == [64, 64]
    assert err.strip().splitlines() == ["explorer: --input is deprecated, use --input-size (the old name goes in "
                                        "the next version)"]
    code, _, err = run_cli("train", "tiny", "--input-size", "32x32")   # refused at once: 16 candidates
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 2 and "--input-size is deprecated, use --train-size" in lines[0]
    assert "holds 16 candidates" in lines[1]


@pytest.mark.parametrize("command", ("supernet train", "search"))
def test_head_kinds_offers_what_the_supernet_trains(command):
    from explorer.supernet import HEAD_KINDS, SupernetRecipe
    action = _visible(command)["--head-kinds"]
    assert set(action.choices) == set(HEAD_KINDS) and action.default == SupernetRecipe().head_kinds
