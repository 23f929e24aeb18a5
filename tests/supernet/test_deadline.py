"""A search's time limit can stop the supernet short of its steps; the file resumes later."""

import time

from conftest import TINY_DATA
from explorer.space import SearchSpace
from explorer.supernet import SupernetRecipe, read_supernet, train_supernet


def test_a_deadline_stops_training_and_a_later_call_finishes_it(tmp_path):
    space = SearchSpace.from_yaml("tiny")
    recipe = SupernetRecipe(steps=3, batch_size=4, input_size=(32, 32))
    out = train_supernet(space, TINY_DATA, recipe, tmp_path / "s.pt", deadline=time.time())
    state = read_supernet(out)
    assert state["step"] == 0 and not state.get("complete")
    train_supernet(space, TINY_DATA, recipe, out)
    assert read_supernet(out)["step"] == 3 and read_supernet(out)["complete"]
