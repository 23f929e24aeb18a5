"""``exits.cascade``: a dimension of the space (only where its residual exits can be chosen), left out of
a candidate's dict at its default, and not offered by the default space."""

import dataclasses

import optuna
import pandas as pd
import pytest

from explorer.cost.enumerate import candidate_rows, enumerate_space, space_grid
from explorer.space import SearchSpace

TINY = {"name": "t", "image_encoder": {"blocks": [2, 3], "width_mult": [0.25]},
        "lidar_encoder": {"depth": [2], "width": [8]}, "ecu": {"enabled": [True], "band": [1], "width": [16]},
        "decoder": {"widths": [[16, 32], [8]]}, "exits": {"optional": [0, 1], "head_depth": [1], "head_width": [8]}}


def _space(**exits) -> SearchSpace:
    return SearchSpace.from_dict({**TINY, "exits": {**TINY["exits"], **exits}})


def test_the_default_space_offers_no_cascade():
    space = SearchSpace.from_yaml("anytime_depth")
    assert space.exit_cascade == (False,) and "exit_cascade" not in space.dimensions()


@pytest.mark.parametrize("residual,cascade,modes", [
    ([False, True], [False, True], [(False, False), (True, False), (True, True)]),
    ([True], [False, True], [(True, False), (True, True)]),
    ([True], [True], [(True, True)]),
    ([False], [False, True], [(False, False)]),     # no residual exits: nothing to cascade
])
def test_a_cascade_is_a_choice_only_beside_residual_exits(residual, cascade, modes):
    space = _space(residual=residual, cascade=cascade)
    assert space.exit_modes() == modes
    every = list(space.enumerate())
    assert len(every) == len(set(every)) == space.size == len(list(_space().enumerate())) * len(modes)
    assert {(c.exit_residual, c.exit_cascade) for c in every} == set(modes)
    assert all(space.contains(c) for c in every)
    assert ("exit_cascade" in space.dimensions()) == (len(modes) == 3 or modes == [(True, False), (True, True)])
    if (True, True) not in modes:
        assert not _space(residual=[True]).contains(dataclasses.replace(every[0], exit_residual=True, exit_cascade=True))


def test_a_trial_draws_the_cascade_only_with_residual_exits():
    space = _space(residual=[False, True], cascade=[False, True])
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    seen = set()
    for _ in range(40):
        trial = study.ask()
        cand = space.sample(trial)
        assert ("exit_cascade" in trial.params) == cand.exit_residual
        assert space.params_of(cand) == trial.params
        seen.add((cand.exit_residual, cand.exit_cascade))
        study.tell(trial, 0.0)
    assert seen == set(space.exit_modes())


def test_the_space_table_costs_every_cascade_candidate_as_one_at_a_time():
    space = _space(residual=[False, True], cascade=[False, True])
    budget, size = "time:uniform:4ms", (32, 32)
    grid = space_grid(space, "tx2", budget, size)
    assert [grid.candidate(i) for i in range(grid.size)] == list(space.enumerate())
    want = pd.DataFrame(list(candidate_rows(space, "tx2", budget, size)))
    pd.testing.assert_frame_equal(enumerate_space(space, "tx2", budget, size), want, check_exact=True)
