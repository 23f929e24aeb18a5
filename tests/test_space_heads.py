"""Exit heads sized for their position (``exits.encoder_head_*``, ``exits.ecu_head_*``): dimensions drawn
only where the position has an exit, left out of a candidate's dict at their default, not offered by
the default space."""

import dataclasses

import optuna
import pytest

from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace, fastdepth_candidate, paper_candidate, paper_nee_candidate

TINY = {"name": "t", "image_encoder": {"blocks": [3], "width_mult": [0.25], "exits": [2]},
        "lidar_encoder": {"depth": [2], "width": [8]}, "ecu": {"enabled": [True], "band": [1], "width": [16]},
        "decoder": {"widths": [[16, 32], [8]]}, "exits": {"optional": [0, 1], "head_depth": [1, 2], "head_width": [8]}}


def _space(**exits) -> SearchSpace:
    return SearchSpace.from_dict({**TINY, "exits": {**TINY["exits"], **exits}})


def test_default_candidates_keep_their_keys_and_the_default_space_offers_no_per_position_heads():
    # the keys these candidates had before heads could be sized per position
    assert paper_candidate().key == "82c6b306e5" and fastdepth_candidate().key == "f82eab0417"
    assert "ecu_head_depth" not in paper_nee_candidate().to_dict()
    dims = SearchSpace.from_yaml("anytime_depth").dimensions()
    assert not any("_head_" in k and k.split("_")[0] in ("encoder", "ecu") for k in dims)


def test_a_head_sized_for_its_position_is_canonical():
    base = Candidate(encoder_blocks=3, width_mult=0.25, lidar_depth=2, lidar_width=8, ecu_band=1, ecu_width=16,
                     decoder_widths=(16, 8), exits=(0, 2), encoder_exits=(2,), head_depth=2, head_width=8)
    same = dataclasses.replace(base, ecu_head_depth=2, ecu_head_width=8, encoder_head_depth=2)
    assert same == base and same.key == base.key
    narrow = dataclasses.replace(base, ecu_head_width=4)
    assert narrow.key != base.key and narrow.head("ecu") == (2, 4) and narrow.head("encoder") == (2, 8)
    assert Candidate.from_dict(narrow.to_dict()) == narrow and "ECU exit: 2 pw convs (4 ch)" in narrow.describe()
    one = dataclasses.replace(base, encoder_head_depth=1, encoder_head_width=16)
    assert one.head("encoder") == (1, 0) and one.encoder_head_width == 0
    # no exit at the position: nothing to size
    assert dataclasses.replace(base, exits=(2,), ecu_head_width=4) == dataclasses.replace(base, exits=(2,))
    with pytest.raises(UserError, match="1 or 2 pointwise"):
        dataclasses.replace(base, ecu_head_depth=3)


@pytest.mark.parametrize("exits", [
    {"ecu_head_depth": [1, 2], "ecu_head_width": [4, 16]},
    {"encoder_head_depth": [1, 2], "encoder_head_width": [4]},
    {"ecu_head_width": [4, 8, 16], "encoder_head_depth": [2], "encoder_head_width": [4, 16]},
    {"required": [0], "optional": [1], "ecu_head_depth": [2], "ecu_head_width": [4, 16]},
])
def test_a_space_enumerates_samples_and_contains_per_position_heads(exits):
    space = _space(**exits)
    every = list(space.enumerate())
    assert len(every) == len(set(every)) == space.size > _space(**{k: v for k, v in exits.items()
                                                                     if "_head_" not in k}).size
    assert all(space.contains(c) for c in every)
    assert any(c.ecu_head_depth or c.ecu_head_width or c.encoder_head_depth or c.encoder_head_width for c in every)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    seen = set()
    for _ in range(60):
        trial = study.ask()
        cand = space.sample(trial)
        assert space.params_of(cand) == trial.params and cand in set(every)
        assert ("ecu_head_depth" in trial.params) <= (0 in cand.exits)
        assert ("encoder_head_depth" in trial.params) <= bool(cand.encoder_exits)
        seen.add(cand)
        study.tell(trial, 0.0)
    assert len(seen) > len(every) // 3
    assert len(space.random_candidates(len(every), seed=1)) == len(every)


def test_a_space_without_the_position_does_not_draw_its_heads():
    space = _space(optional=[1], ecu_head_width=[4, 16])
    assert "ecu_head_width" not in space.dimensions() and space.size == _space(optional=[1]).size
    with pytest.raises(UserError, match="1 or 2 pointwise"):
        _space(ecu_head_depth=[3])


def test_the_space_table_refuses_per_position_heads_in_one_line():
    from explorer.cost.enumerate import candidate_rows, space_grid
    space = _space(ecu_head_width=[4, 16])
    with pytest.raises(UserError, match="one at a time"):
        space_grid(space, "tx2", "time:uniform:4ms", (32, 32))
    rows = list(candidate_rows(space, "tx2", "time:uniform:4ms", (32, 32)))   # one at a time, every candidate
    assert len(rows) == space.size == len({r["key"] for r in rows})


def test_a_space_that_does_not_size_heads_per_position_does_not_contain_such_candidates():
    sized = [c for c in _space(ecu_head_width=[4, 16]).enumerate() if c.ecu_head_width]
    plain = _space()
    assert sized and not any(plain.contains(c) for c in sized)
    assert all(plain.contains(dataclasses.replace(c, ecu_head_width=0)) for c in sized)
