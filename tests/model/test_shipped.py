import math

import pytest
import torch

from explorer.cost import candidate_cost, get_device
from explorer.model import build_network
from explorer.model.shipped import carry_weights, exit_names, last_path_note, ship, without_exits
from explorer.space import Candidate, paper_candidate

#: every kind of exit: the LiDAR-only one, two encoder exits (fused with the LiDAR feature), the ECU's,
#: decoder exits, residual heads
WIDE = Candidate(encoder_blocks=6, width_mult=0.25, lidar_depth=4, lidar_width=8, ecu_band=1, ecu_width=16,
                 decoder_widths=(32, 16, 16, 8), exits=(0, 1, 2, 4), head_depth=2, head_width=8,
                 encoder_exits=(3, 5), lidar_exit=True, lidar_first=True, exit_residual=True)


def test_exit_names_follow_the_paths():
    assert exit_names(WIDE) == ["lidar_exit", "exit_b3", "exit_b5", "exit_0", "exit_1", "exit_2", "exit_4"]
    assert len(exit_names(WIDE)) == WIDE.num_paths - 1


def test_each_exit_that_does_not_improve_on_an_earlier_path_is_dropped_the_last_never():
    #          scan  lidar  b3    b5    ECU   1     2     4
    losses = [0.90, 0.70, 0.75, 0.60, 0.60, 0.50, 0.55, 0.58]
    shipped = ship(WIDE, losses)
    assert [(d.path, d.exit, d.better_path) for d in shipped.dropped] == [
        (2, "exit_b3", 1), (4, "exit_0", 3), (6, "exit_2", 5)]
    assert shipped.paths == (0, 1, 3, 5, 7)   # the last path stays: the decoder always exits there
    assert shipped.candidate.encoder_exits == (5,) and shipped.candidate.exits == (1, 4)
    assert shipped.candidate.lidar_exit and shipped.candidate.num_paths == 5
    assert shipped.losses(losses) == [0.90, 0.70, 0.60, 0.50, 0.58]
    assert ship(WIDE, losses, keep_every_exit=True).candidate == WIDE


def test_a_path_no_better_than_the_scan_is_dropped_and_a_nan_never_improves():
    shipped = ship(paper_candidate(), [0.5, 0.5, float("nan"), 0.4, 0.3])
    assert [d.path for d in shipped.dropped] == [1, 2]
    assert shipped.candidate.exits == (2, 4)
    assert math.isnan(shipped.dropped[1].loss)
    assert ship(paper_candidate(), [0.9, 0.8, 0.7, 0.6, 0.5]).dropped == ()


def test_the_last_exit_cannot_be_left_out():
    with pytest.raises(ValueError, match="last decoder stage"):
        without_exits(paper_candidate(), ["exit_4"])


@pytest.mark.parametrize("drop", [["exit_b3"], ["exit_b5", "lidar_exit"], ["exit_b3", "exit_b5", "exit_0"],
                                  ["exit_1", "exit_2"]])
def test_the_shipped_network_computes_the_kept_paths_exactly_as_the_trained_one(drop):
    torch.manual_seed(0)
    trained = build_network(WIDE).eval()
    for p in trained.parameters():   # weights unlike their initial values, so a misplaced one shows
        p.data.normal_(0, 0.1)
    shipped_candidate = without_exits(WIDE, drop)
    shipped = build_network(shipped_candidate).eval()
    shipped.load_state_dict(carry_weights(trained.state_dict(), WIDE, shipped_candidate), strict=True)
    image, scan = torch.rand(2, 3, 64, 64), torch.rand(2, 64) * 5 + 0.5
    with torch.no_grad():
        full, kept = trained(image, scan), shipped(image, scan)
    names = ["scan"] + exit_names(WIDE)
    expected = [d for d, name in zip(full, names) if name not in drop]
    assert len(kept) == len(expected) == WIDE.num_paths - len(drop)
    for a, b in zip(kept, expected):
        torch.testing.assert_close(a, b)


def test_later_paths_are_ready_sooner_once_a_head_is_dropped():
    tx2 = get_device("tx2")
    full = candidate_cost(WIDE).path_latency_ms(tx2)
    shipped = ship(WIDE, [0.9, 0.8, 0.85, 0.7, 0.6, 0.5, 0.4, 0.3])   # exit_b3 dropped
    kept = candidate_cost(shipped.candidate).path_latency_ms(tx2)
    assert kept[0] == 0.0 and kept[1] == pytest.approx(full[1])
    assert all(k < f for k, f in zip(kept[2:], full[3:]))


def test_a_last_path_no_better_than_an_earlier_one_is_said_with_the_path_a_halt_returns():
    note = last_path_note([0.50, 0.40, 0.30, 0.31, 0.32], "rmse")
    assert note is not None
    assert "path 4" in note and "path 2's rmse" in note and "0.32 against 0.3" in note
    assert note.endswith("returns path 2")
    assert "path 1's" in last_path_note([0.5, 0.4, 0.4])          # equal is not more accurate
    assert last_path_note([0.50, 0.40, 0.30, 0.29]) is None
    assert last_path_note([0.50, math.nan, 0.45]) is None           # a path measured nothing is no rival
    assert last_path_note([0.50, 0.40, math.nan]) is None           # nor is a last path without a figure
    assert last_path_note([0.50]) is None
