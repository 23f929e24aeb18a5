"""The envelope's steps: each budget served by the most accurate dedicated network ready by it."""

import dataclasses

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
    assert "ready at 7.1, 10.6 ms" in below.below_one and "only the scan" in below.below_one
    assert Envelope([0.0, 7.1], [0.53, 0.38], loss=0.38, winner_loss=0.40, networks=[{}]).below_one is None
    assert Envelope([0.0, 7.1], [0.53, 0.38], loss=0.38, winner_loss=None, networks=[{}]).below_one is None


def test_each_path_of_a_candidate_has_its_dedicated_network_trained_for_it_alone():
    from explorer.space import paper_candidate
    from explorer.study.config import SearchConfig
    from explorer.study.envelope import dedicated, dedicated_networks
    candidate = paper_candidate()
    networks = dedicated_networks(candidate)
    assert [n.path for n in networks[:-1]] == list(range(1, candidate.num_paths - 1))
    assert networks[-1].candidate == dedicated(candidate) and networks[-1].path == 1
    assert len({n.key for n in networks}) == len(networks)
    base = SearchConfig(study="s").finalist_recipe()
    assert networks[-1].recipe(base) == base                        # a single exit: the finalists' recipe
    early = networks[0].recipe(base)
    assert early.train.exit_weights == (1.0,) + (0.0,) * (candidate.num_paths - 2)
    assert early.tune_config().exit_weights == early.train.exit_weights   # the tuning too
    assert dataclasses.replace(early.train, exit_weights=None) == base.train


def test_a_path_with_no_weight_takes_no_gradient():
    import torch

    from explorer.training.train import multi_exit_loss
    outputs = [torch.zeros(1, 1, 2, 2)] + [torch.zeros(1, 1, 2, 2, requires_grad=True) for _ in range(3)]
    total, _ = multi_exit_loss(outputs, torch.ones(1, 1, 2, 2), (0.0, 1.0, 0.0))
    total.backward()
    assert [float(o.grad.abs().sum()) for o in outputs[1:]] == [0.0, 4.0 / 4, 0.0]


def test_the_networks_are_spread_along_the_estimated_front():
    """The front (each point more accurate than every cheaper one) runs from 2 to 10 ms: the points
    nearest 2, 4.67, 7.33 and 10 ms; a point off the front (11 ms, no better than the 10 ms one) or
    no better than a cheaper one (5 ms) is never chosen."""
    from explorer.study.envelope import spread_along_front
    points = [(2.0, 0.50, "a"), (3.0, 0.45, "b"), (4.5, 0.42, "c"), (5.0, 0.43, "off"), (7.0, 0.38, "d"),
              (8.0, 0.37, "e"), (10.0, 0.33, "f"), (11.0, 0.35, "worse")]
    assert spread_along_front(points, 4) == ["a", "c", "d", "f"]
    assert spread_along_front(list(reversed(points)), 4) == ["a", "c", "d", "f"]     # in any order
    assert spread_along_front(points, 9) == ["a", "b", "c", "d", "e", "f"]          # the whole front


def test_a_point_already_chosen_leaves_a_deadline_to_the_next_nearest():
    """Costs 0.5, 33.7, 66.8 and 100 ms: 33.7 takes d, 66.8 takes e (nearer than c), so 100 takes the
    nearest left, c."""
    from explorer.study.envelope import spread_along_front
    points = [(0.5, 0.50, "a"), (1.0, 0.49, "b"), (2.0, 0.48, "c"), (3.0, 0.47, "d"), (100.0, 0.30, "e")]
    assert spread_along_front(points, 4) == ["a", "c", "d", "e"]


def test_the_envelope_command_names_the_storage_where_the_study_is_not_in_its_local_journal(tmp_path):
    from explorer.study.envelope import envelope_command
    from explorer.study.storage import local_url
    assert envelope_command("s") == "explorer envelope --study s"
    assert envelope_command("s", local_url("s")) == "explorer envelope --study s"
    assert envelope_command("s", local_url("s", tmp_path), tmp_path) == f"explorer envelope --study s --reports {tmp_path}"
    shared = envelope_command("s", "postgresql://me:secret@db.lab:5432/studies")
    assert shared == "explorer envelope --study s --storage postgresql://me:***@db.lab:5432/studies"
    assert envelope_command("s", "journal:/nfs/s.log").endswith("--storage journal:/nfs/s.log")


def _shipped_envelope_record(path: int, trained_paths: list[int], dropped: list[dict]):
    from types import SimpleNamespace
    return SimpleNamespace(envelope=SimpleNamespace(path=path), path_metrics=[{}] * len(trained_paths),
                           shipped=SimpleNamespace(trained_paths=trained_paths, dropped=dropped))


def test_a_dedicated_network_is_read_at_its_path_as_it_ships():
    """Its other exits, trained with no weight, were left out of what ships: its figures are the shipped
    network's, so its path stands where the shipped paths put it; numbered as trained, it keeps its key."""
    from explorer.study.envelope import dedicated_path, served_index
    rec = _shipped_envelope_record(3, [0, 3, 4], [{"path": 1, "better_path": 0}, {"path": 2, "better_path": 0}])
    assert dedicated_path(rec) == 3 and served_index(rec) == 1
    # its own exit no more accurate than the scan: the scan serves in its place
    rec = _shipped_envelope_record(2, [0, 4], [{"path": 1, "better_path": 0}, {"path": 2, "better_path": 0},
                                               {"path": 3, "better_path": 0}])
    assert served_index(rec) == 0
    kept = _shipped_envelope_record(2, [0, 1, 2, 3], [])
    kept.shipped = None
    assert served_index(kept) == 2
