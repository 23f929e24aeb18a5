import dataclasses
import random

import pytest

from conftest import TINY_DATA
from explorer.errors import UserError
from explorer.space import SearchSpace
from explorer.supernet import (SupernetRecipe, cache_key, describe_fidelity, largest_candidate, measured_fidelity,
                               smallest_candidate, store_fidelity, train_supernet)
from explorer.supernet.train import _subnets


@pytest.fixture(scope="module")
def default_space():
    return SearchSpace.from_yaml("anytime_depth")


def _kinds(space, recipe, step):
    subnets = _subnets(largest_candidate(space), smallest_candidate(space), space, recipe, step,
                       random.Random(step))
    return [(c.head_depth, c.exit_residual) for c in subnets]


def test_covering_head_kinds_trains_every_kind_every_other_step(default_space):
    recipe = SupernetRecipe(head_kinds="cover", shrink=0.0)   # the smallest in its place every step
    every = {(d, r) for d in default_space.head_depth for r in default_space.exit_residual}
    for step in range(6):
        assert set(_kinds(default_space, recipe, step) + _kinds(default_space, recipe, step + 1)) == every
    two = dataclasses.replace(recipe, random_subnets=2)
    assert all(set(_kinds(default_space, two, step)) == every for step in range(4))
    for step in range(4):   # a covering subnet is a valid candidate: depth-2 heads have a width, depth-1 none
        for c in _subnets(largest_candidate(default_space), smallest_candidate(default_space), default_space,
                          two, step, random.Random(step))[2:]:
            assert default_space.contains(dataclasses.replace(c, exits=(4,), encoder_exits=(), lidar_exit=False))


def test_rotating_head_kinds_trains_every_kind_on_every_backbone(default_space):
    recipe = SupernetRecipe(head_kinds="rotate")
    every = {(d, r) for d in default_space.head_depth for r in default_space.exit_residual}
    seen = {kind: set() for kind in every}           # kind -> the subnet positions (teacher, smallest, random)
    for step in range(4):
        for position, kind in enumerate(_kinds(default_space, recipe, step)):
            seen[kind].add(position)
    assert all(positions == {0, 1, 2} for positions in seen.values())
    four = dataclasses.replace(recipe, random_subnets=2)
    assert all(set(_kinds(default_space, four, step)) == every for step in range(4))
    subnets = _subnets(largest_candidate(default_space), smallest_candidate(default_space), default_space,
                       four, 1, random.Random(1))
    for c in subnets:    # each is still a valid candidate of the space
        assert default_space.contains(dataclasses.replace(c, exits=(4,), encoder_exits=(), lidar_exit=False))


def test_random_head_kinds_keep_the_cache_key_of_earlier_supernets(default_space):
    before = SupernetRecipe(head_kinds="random")
    assert "head_kinds" not in before.identity()
    keys = {cache_key(default_space, "synthetic", SupernetRecipe(head_kinds=k)) for k in ("random", "cover", "rotate")}
    assert len(keys) == 3


def test_a_file_made_before_head_kinds_reads_as_random():
    old = SupernetRecipe(head_kinds="random").to_dict()
    del old["head_kinds"]
    assert SupernetRecipe.from_dict(old).head_kinds == "random"
    assert SupernetRecipe.from_dict(SupernetRecipe().to_dict()).head_kinds == "rotate"


def test_an_unknown_head_kinds_is_refused(tmp_path):
    with pytest.raises(UserError, match="rotate, cover, random"):
        train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, SupernetRecipe(head_kinds="all"), tmp_path / "s.pt")


def test_a_stored_fidelity_is_found_for_every_seed_of_its_recipe_only(default_space, tmp_path):
    file = tmp_path / "fidelity.json"
    recipe = SupernetRecipe(steps=600)
    assert measured_fidelity(default_space, "synthetic", recipe, file) is None
    entry = {"tau": [0.71, 0.74], "spearman": [0.88, 0.9], "recall": [4, 5], "candidates": 24, "label_steps": 1200,
             "labels_seed_tau": 0.8, "date": "2026-11-26"}
    store_fidelity(default_space, "synthetic", recipe, entry, file)
    found = measured_fidelity(default_space, "synthetic", dataclasses.replace(recipe, seed=3), file)
    assert found["tau"] == [0.71, 0.74] and found["space"] == "anytime_depth"
    assert measured_fidelity(default_space, "synthetic", dataclasses.replace(recipe, steps=300), file) is None
    assert measured_fidelity(default_space, "kitti", recipe, file) is None
    text = describe_fidelity(found)
    assert "Kendall tau 0.71-0.74" in text and "4-5 of the best 5" in text and "1200 steps" in text
    assert "unmeasured" in describe_fidelity(None)
    assert ", 3 of the best 5" in describe_fidelity({**entry, "recall": [3, 3]})
    assert "finalists' recipe" not in text
    assert "finalists' recipe rank them at 0.70" in describe_fidelity({**entry, "finalist_tau": 0.698})


def test_the_shipped_record_reads(default_space):
    # whatever the benchmark stored last: every entry has what the summary quotes
    from explorer.supernet.fidelity import load_record
    for entry in load_record().values():
        assert describe_fidelity(entry).startswith("the supernet's ranking")


def test_the_default_search_quotes_a_measured_fidelity(default_space):
    from explorer.study.config import SearchConfig
    config = SearchConfig(study="default")
    entry = measured_fidelity(default_space, config.data, config.supernet_recipe())
    assert entry is not None, "the default recipe changed: measure it (python -m experiments.fidelity --only fidelity --store)"
    assert len(entry["tau"]) >= 2 and entry["candidates"] >= 24
    assert "Kendall tau" in describe_fidelity(entry)


def _widths(c):
    return c.width_mult, c.decoder_widths, c.lidar_width, c.ecu_width


def test_progressive_shrinking_trains_full_widths_first_then_every_width(default_space):
    recipe = SupernetRecipe(steps=100, shrink=0.5)
    largest = largest_candidate(default_space)
    early = [c for step in range(50) for c in _subnets(largest, smallest_candidate(default_space), default_space,
                                                        recipe, step, random.Random(step))]
    late = [c for step in range(50, 100) for c in _subnets(largest, smallest_candidate(default_space), default_space,
                                                           recipe, step, random.Random(step))]
    assert all(c.width_mult == largest.width_mult and c.decoder_widths == largest.decoder_widths for c in early)
    assert all(c.lidar_width == largest.lidar_width for c in early if c.ecu)
    assert len({c.encoder_blocks for c in early}) > 1 and len({c.ecu for c in early}) == 2   # depths still vary
    assert len({_widths(c) for c in late}) > 10
    for c in early + late:
        assert default_space.contains(dataclasses.replace(c, exits=(4,), encoder_exits=(), lidar_exit=False))


def test_shrinking_keeps_the_cache_keys_of_supernets_trained_without_it_and_reads_their_files():
    plain = SupernetRecipe(shrink=0.0)
    assert "shrink" not in plain.identity()
    assert SupernetRecipe().identity()["shrink"] == 0.5     # the default shrinks: a supernet of its own
    old = plain.to_dict()
    del old["shrink"]
    assert SupernetRecipe.from_dict(old).shrink == 0.0


@pytest.mark.parametrize("shrink", [-0.1, 1.0])
def test_a_shrink_fraction_outside_0_to_1_is_refused(tmp_path, shrink):
    with pytest.raises(UserError, match="--shrink"):
        train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, SupernetRecipe(shrink=shrink), tmp_path / "s.pt")
    assert not (tmp_path / "s.pt").exists()
