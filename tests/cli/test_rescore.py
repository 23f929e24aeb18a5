"""explorer rescore keeps what was measured and what the search estimated apart, says which to trust and
how to measure an estimate, and its tables fit 80 columns without a cell broken inside a word."""

import re
from types import SimpleNamespace

import pandas as pd

from explorer.cli._rescore import advice, print_rescored

BUDGETS = ["time:uniform:100ms", "energy:uniform:0.5J"]


def _frame() -> pd.DataFrame:
    """As explorer.study.results.rescore returns it: measured first, each kind sorted by the first budget."""
    rows = [(12, "", "3f9a1c02be", "measured", 0.4033), (15, "paper", "77aa01bc3d", "measured", 0.4512),
            (3, "", "c0ffee1234", "estimate", 0.3886), (5, "", "deadbeef99", "estimate", 0.3920),
            (7, "paper-nee", "0123456789", "estimate", 0.4410)]
    return pd.DataFrame([{"number": n, "baseline": b, "candidate_key": k, "figures": f, BUDGETS[0]: v,
                          BUDGETS[1]: v / 2, "first_exit_ms": 12.25, "last_exit_ms": 88.5, "params": 1_489_000}
                         for n, b, k, f, v in rows])


def test_the_advice_names_the_measured_pick_and_how_to_measure_a_lower_estimate():
    words = advice("s", _frame(), BUDGETS[0], ("224x224", "64x64"), "supernet")
    assert "Pick from the measured table: trial 12 (0.4033) is the best measured" in words
    assert "Trial 3's estimate (0.3886) looks lower but is not comparable" in words
    assert "the supernet's figure at 64x64, not a measurement" in words
    assert "`explorer export --study s --trial 3 --out trial3/`" in words and "--finalists" in words
    only_estimates = advice("s", _frame().iloc[2:], BUDGETS[0], ("224x224", "64x64"), "supernet")
    assert only_estimates.startswith("Nothing is measured yet")


def test_measured_and_estimated_are_two_tables_that_fit_80_columns(monkeypatch, capsys):
    from explorer import console as console_module
    monkeypatch.setattr(console_module.console, "width", 80)
    view = SimpleNamespace(config=SimpleNamespace(input_size=(224, 224), train_size=(64, 64), evaluator="supernet"))
    args = SimpleNamespace(study="s", device="rpi4", metric="rmse", budget=BUDGETS, top=15)
    print_rescored(view, _frame(), args)
    out = capsys.readouterr().out
    lines = out.splitlines()
    measured = next(i for i, line in enumerate(lines) if "measured (2): retrained alone, measured at 224x224" in line)
    estimates = next(i for i, line in enumerate(lines) if "estimates of the search (3): supernet at 64x64" in line)
    row = lambda key: next(i for i, line in enumerate(lines) if key in line)  # noqa: E731
    assert measured < row("3f9a1c02be") < row("paper ") < estimates < row("c0ffee1234") < row("paper-nee")
    assert "Pick from the measured table" in lines[-1] or "Pick from the measured table" in out
    table = [line for line in lines if line[:1] in "┃│┏┡└━┗┌"]
    assert table and max(len(line) for line in table) <= 80
    # every cell whole: keys, names and headers are on one line each
    for token in ("3f9a1c02be", "c0ffee1234", "paper-nee", "L_T@100ms", "L_E@0.5J", "first ms", "1489000"):
        assert any(token in line for line in table), token
    assert not re.search(r"L_T@1\s*│", out)
