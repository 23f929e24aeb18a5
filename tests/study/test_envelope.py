"""The envelope's steps: each budget served by the most accurate dedicated network ready by it."""

import pytest

from explorer.anytime import anytime_loss
from explorer.study.envelope import envelope_steps


def test_a_network_no_better_than_a_cheaper_one_serves_no_budget():
    costs, errors = envelope_steps(0.9, [(20.0, 0.5), (10.0, 0.6), (15.0, 0.7), (30.0, 0.55), (5.0, 1.2)])
    assert costs == [0.0, 10.0, 20.0]
    assert errors == [0.9, 0.6, 0.5]


def test_its_anytime_loss_is_the_oracles():
    """Under U(0, 30 ms): the scan for the first 10 ms, the 10 ms network for the next 10, the best after."""
    costs, errors = envelope_steps(0.9, [(10.0, 0.6), (20.0, 0.5)])
    assert anytime_loss(costs, errors, "time:uniform:30ms") == pytest.approx((0.9 + 0.6 + 0.5) / 3)


def test_with_no_network_better_than_the_scan_the_scan_serves_every_budget():
    assert envelope_steps(0.4, [(10.0, 0.6)]) == ([0.0], [0.4])


def test_the_commands_default_is_the_one_the_summary_names():
    from explorer.cli import build_parser
    from explorer.study.envelope import DEFAULT_NETWORKS
    assert build_parser().parse_args(["envelope", "--study", "s"]).networks == DEFAULT_NETWORKS


def test_a_winner_below_the_envelope_is_told_why():
    from explorer.study.envelope import Envelope
    below = Envelope([0.0, 7.1, 10.6], [0.53, 0.38, 0.33], loss=0.38, winner_loss=0.35, networks=[{}, {}])
    assert below.ratio == pytest.approx(0.35 / 0.38)
    assert "(7.1 ms)" in below.below_one and "only the scan" in below.below_one
    assert Envelope([0.0, 7.1], [0.53, 0.38], loss=0.38, winner_loss=0.40, networks=[{}]).below_one is None
    assert Envelope([0.0, 7.1], [0.53, 0.38], loss=0.38, winner_loss=None, networks=[{}]).below_one is None
