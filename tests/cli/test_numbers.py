"""Numbers on the command line are bounded and written in ASCII digits, for every command, before any
work starts: one line, exit 2."""

import pytest


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
