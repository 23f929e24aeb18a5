import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from explorer.anytime import (TruncatedNormal, Uniform, anytime_curve, anytime_loss, check_losses, exit_loss_weights,
                              returned_losses,
                              parse_budget)
from explorer.errors import UserError


def test_eq1_by_hand():
    # U(0, 10): path 0 on [0, 2), path 1 on [2, 5), path 2 on [5, 10)
    got = anytime_loss([0, 2, 5], [1.0, 0.5, 0.2], "time:uniform:10ms")
    assert got == pytest.approx((1.0 * 2 + 0.5 * 3 + 0.2 * 5) / 10)


def test_path_beyond_budget_never_counts():
    # path 2 needs 12 ms > B_max = 10 ms: path 1 holds until the end
    got = anytime_loss([0, 4, 12], [1.0, 0.5, 0.1], "time:uniform:10ms")
    assert got == pytest.approx((1.0 * 4 + 0.5 * 6) / 10)


def test_single_path_network():
    assert anytime_loss([0, 6], [0.9, 0.4], "time:uniform:12ms") == pytest.approx((0.9 * 6 + 0.4 * 6) / 12)
    assert anytime_loss([0], [0.9], "time:uniform:12ms") == pytest.approx(0.9)


def test_exit_loss_weights_follow_each_exit_share_of_the_anytime_loss():
    # U(0, 10): path 1 holds on [2, 5), path 2 on [5, 10), path 3 (at 12 ms) never
    assert exit_loss_weights([0, 2, 5, 12], "time:uniform:10ms", floor=0.0) == pytest.approx((3 / 8, 5 / 8, 0.0))
    mixed = exit_loss_weights([0, 2, 5, 12], "time:uniform:10ms", floor=0.3)
    assert mixed == pytest.approx((0.7 * 3 / 8 + 0.1, 0.7 * 5 / 8 + 0.1, 0.1)) and sum(mixed) == pytest.approx(1)
    # no exit within the budget at all: equal weights
    assert exit_loss_weights([0, 20, 30], "time:uniform:10ms") == pytest.approx((0.5, 0.5))
    with pytest.raises(UserError, match="floor"):
        exit_loss_weights([0, 2], "time:uniform:10ms", floor=1.5)


def test_energy_and_units():
    assert anytime_loss([0, 0.1, 0.3], [1, 0.5, 0.25], "energy:uniform:500mJ") == pytest.approx(
        (0.1 * 1 + 0.2 * 0.5 + 0.2 * 0.25) / 0.5)
    assert parse_budget("time:uniform:0.033s").maximum == pytest.approx(33)


def test_other_distributions_by_hand(tmp_path):
    costs, losses = [0, 5], [1.0, 0.2]
    p = 1 - np.exp(-5 / 10)
    assert anytime_loss(costs, losses, "time:exponential:10ms") == pytest.approx(1.0 * p + 0.2 * (1 - p))
    trace = tmp_path / "deadlines.csv"
    trace.write_text("deadline_ms\n2\n4\n6\n8\n")
    assert anytime_loss(costs, losses, f"time:trace:{trace}") == pytest.approx(0.5 * 1.0 + 0.5 * 0.2)
    tn = parse_budget("time:truncnormal:5ms:2ms")
    assert isinstance(tn, TruncatedNormal)
    assert anytime_loss(costs, losses, tn) == pytest.approx(0.5 * 1.0 + 0.5 * 0.2, abs=0.02)
    assert tn.cdf(0.0) == pytest.approx(0.0)


def test_curve_area_is_the_loss():
    costs, losses = [0, 2, 5], [1.0, 0.5, 0.2]
    xs, ys = anytime_curve(costs, losses, 10)
    area = float(np.sum(np.diff(xs) * ys[:-1]))
    assert area / 10 == pytest.approx(anytime_loss(costs, losses, Uniform(10.0)))


@pytest.mark.parametrize("spec, msg", [
    ("time:uniform", "incomplete"), ("speed:uniform:3ms", "kind"), ("time:gauss:3ms", "distribution"),
    ("time:uniform:3J", "unit"), ("time:uniform:-3ms", "quantity"), ("time:uniform:0ms", "positive"),
    ("time:trace:/nonexistent.csv", "no such file")])
def test_bad_specs(spec, msg):
    with pytest.raises(UserError, match=msg):
        parse_budget(spec)


def test_bad_costs():
    with pytest.raises(UserError, match="decrease"):
        anytime_loss([0, 5, 3], [1, 1, 1], "time:uniform:10ms")
    with pytest.raises(UserError, match="same length"):
        anytime_loss([0, 5], [1], "time:uniform:10ms")


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="timeenrgy:uniformexpotlcahs0123456789.e-msJj ", max_size=40))
def test_any_budget_spec_parses_or_is_one_user_error(spec):
    """Whatever a user types after --budget is a distribution with a finite upper end, or one line."""
    try:
        b = parse_budget(spec)
    except UserError as exc:
        assert "\n" not in str(exc)
        return
    assert np.isfinite(b.upper) and b.upper > 0


@pytest.mark.parametrize("spec", ["time:uniform:1e400ms", "time:uniform:0ms", "time:exponential:0ms"])
def test_infinite_or_zero_budgets_are_refused(spec):
    with pytest.raises(UserError):
        parse_budget(spec)


def test_a_trace_of_zeros_or_infinities_is_refused(tmp_path):
    for name, values in (("zeros", "0\n0\n0\n"), ("inf", "1\ninf\n2\n")):
        path = tmp_path / f"{name}.csv"
        path.write_text("deadline_ms\n" + values)
        with pytest.raises(UserError, match="deadline"):
            parse_budget(f"time:trace:{path}")


@pytest.mark.parametrize("losses", [[0.5, float("nan")], [0.5, -0.1], [float("inf"), 1.0]])
def test_losses_a_user_gives_must_be_finite_and_non_negative(losses):
    with pytest.raises(UserError, match="losses"):
        check_losses(losses)


def test_a_halt_returns_the_most_accurate_path_ready_never_a_worse_later_one():
    # path 2 is less accurate than path 1: a halt after it still returns path 1's map
    costs, losses = [0.0, 10.0, 20.0, 30.0], [0.9, 0.5, 0.6, 0.4]
    assert list(returned_losses(losses)) == [0.9, 0.5, 0.5, 0.4]
    uniform = anytime_loss(costs, losses, "time:uniform:40ms")
    assert uniform == pytest.approx((10 * 0.9 + 10 * 0.5 + 10 * 0.5 + 10 * 0.4) / 40)
    # where every path improves, nothing changes (the paper's Eq. 1)
    assert anytime_loss(costs, [0.9, 0.6, 0.5, 0.4], "time:uniform:40ms") == pytest.approx(0.6)
    xs, ys = anytime_curve(costs, losses, 40.0)
    assert list(ys) == [0.9, 0.5, 0.5, 0.4, 0.4]


def test_a_trace_without_a_header_keeps_its_first_deadline(tmp_path):
    headed, bare = tmp_path / "headed.csv", tmp_path / "bare.csv"
    headed.write_text("deadline_ms\n20\n5\n5\n5\n")
    bare.write_text("20\n5\n5\n5\n")
    costs, losses = [0.0, 6.4, 12.2], [1.0, 0.465, 0.416]
    loss = anytime_loss(costs, losses, f"time:trace:{bare}")
    assert loss == anytime_loss(costs, losses, f"time:trace:{headed}") == pytest.approx(0.75 * 1.0 + 0.25 * 0.416)
