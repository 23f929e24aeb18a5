"""Bounds (issue 89): numbers on the command line are bounded and written in ASCII digits, for every
command, before any work starts; YAML and JSON nest and expand only so far; a stored device profile out
of its bounds is refused before any trial runs: one line, exit 2, nothing written."""

import time

import pytest

from explorer.errors import UserError
from explorer.files import read_json, read_yaml
from explorer.study import storage
from _faults import fast_search


@pytest.mark.parametrize("args, says", [
    (["search", "--trials", "٣"], "--trials '٣': write numbers with the digits 0-9"),
    (["train", "paper", "--steps", "１０"], "--steps '１０': write numbers with the digits 0-9"),
    (["search", "--timeout", "١m"], "--timeout '١m': write numbers"),
    (["profile", "paper", "--input-size", "٢٢٤x224"], "--input-size '٢٢٤x224': write numbers"),
    (["search", "--seed", "-1"], "--seed -1: must be at least 0"),
    (["search", "--seed", "99999999999999"], "--seed 99999999999999: give at most 4294967295"),
    (["train", "paper", "--seed", "-5"], "--seed -5: must be at least 0"),
    (["train", "paper", "--batch-size=99999999999999999999"], "--batch-size 99999999999999999999: give at most"),
    (["search", "--batch-size", "100000"], "--batch-size 100000: give at most 65536"),
])
def test_a_number_out_of_bounds_or_in_other_digits_is_one_line(run_cli, tmp_path, args, says):
    code, out, err = run_cli(*args, *(["--reports", tmp_path] if args[0] == "search" else []))
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not any(tmp_path.iterdir())


def test_a_damaged_stored_device_profile_is_refused_before_any_trial_runs(tmp_path, run_cli):
    from explorer.cli import build_parser
    from explorer.cli._common import resolve_data
    from explorer.cli.study import _search_context
    from explorer.study.search import create_or_resume
    args = build_parser().parse_args([str(a) for a in fast_search(tmp_path)])
    resolve_data(args)
    study = create_or_resume(_search_context(args), storage.open_storage(None, "cc", reports=tmp_path))
    study.set_user_attr("device_profile", {**study.user_attrs["device_profile"], "body_exponent": 1e6})
    code, _, err = run_cli(*fast_search(tmp_path))
    assert code == 2 and "body_exponent must lie in" in err and len(err.strip().splitlines()) == 1, err
    reread = storage.load_study("cc", reports=tmp_path)
    assert reread.trials == [] and not [p for p in tmp_path.rglob("*search-lock*")]


def test_an_alias_bomb_is_refused_at_once(tmp_path):
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    start = time.monotonic()
    with pytest.raises(UserError, match="aliases expand"):
        read_yaml(path)
    assert time.monotonic() - start < 1.0


@pytest.mark.parametrize("text", ["x: " + "[" * 5000 + "]" * 5000, "{a: " * 3000 + "1" + "}" * 3000,
                                  "- " * 2000 + "1"])
def test_deep_nesting_is_one_line_not_a_recursion_error(tmp_path, text):
    path = tmp_path / "deep.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match="nest more than 100 deep") as caught:
        read_yaml(path)
    assert "\n" not in str(caught.value)
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(UserError, match="nested too deep"):
        read_json(tmp_path / "deep.json")
