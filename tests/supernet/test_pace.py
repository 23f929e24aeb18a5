"""A supernet step's time, as a time limit's plan reads it: both phases of the recipe, weighted."""

import pytest
import torch

from conftest import TINY_DATA
from explorer.space import SearchSpace
from explorer.supernet import SupernetRecipe
from explorer.supernet import pace

#: fake seconds a step takes: warm-up, a step while progressive shrinking, a step after it
WARM, SHRINKING, PLAIN = 10.0, 2.0, 1.0


@pytest.fixture
def fake_clock(monkeypatch):
    """Steps that cost WARM for the first two, then SHRINKING in progressive shrinking's steps (the
    first ``recipe.shrink`` of them) and PLAIN after, on a clock that only steps move."""
    space = SearchSpace.from_yaml("tiny")
    now, done = [0.0], []

    def subnets(largest, smallest, space, recipe, step, rng):
        return [step < recipe.shrink * recipe.steps]    # stands for the step's subnets: its phase

    def step(net, opt, batch, subnets, *args):
        now[0] += WARM if len(done) < 2 else (SHRINKING if subnets[0] else PLAIN)
        done.append(subnets[0])
        return torch.zeros(1)

    monkeypatch.setattr(pace, "_subnets", subnets)
    monkeypatch.setattr(pace, "_sandwich_step", step)
    monkeypatch.setattr(pace.time, "perf_counter", lambda: now[0])
    return space, done


@pytest.mark.parametrize("shrink,expected", [(0.5, 1.5), (0.0, PLAIN), (1.0, SHRINKING), (0.25, 1.25)])
def test_a_step_is_the_phases_weighted_by_their_share_of_the_recipe(fake_clock, shrink, expected):
    space, done = fake_clock
    recipe = SupernetRecipe(steps=8, batch_size=4, input_size=(32, 32), shrink=shrink)
    seconds = pace.seconds_per_step(space, TINY_DATA, recipe, torch.device("cpu"), steps=3, warmup=2)
    assert seconds == pytest.approx(expected)
    # the warm-up, then three steps of each phase the recipe has, in its order
    phases = [True] * 3 * (shrink > 0) + [False] * 3 * (shrink < 1)
    assert done[2:] == phases


def test_a_real_step_takes_time_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    space = SearchSpace.from_yaml("tiny")
    recipe = SupernetRecipe(steps=4, batch_size=4, input_size=(32, 32))
    assert pace.seconds_per_step(space, TINY_DATA, recipe, torch.device("cpu"), steps=1, warmup=1) > 0
    assert list(tmp_path.iterdir()) == []
