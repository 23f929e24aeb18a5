"""bench_held_out (benchmarks/bench_held_out.py) measures the study's winner and the paper design on the
validation frames the study did not choose with."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_held_out import held_out_data, parse_recipes  # noqa: E402

from explorer.data import open_dataset  # noqa: E402
from explorer.study.config import SearchConfig  # noqa: E402

from conftest import TINY_DATA  # noqa: E402


def test_only_the_frames_after_the_studys_are_measured():
    context = SearchConfig(study="held-out", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    data = held_out_data(context, seed=3, val_from=10)
    val = open_dataset(TINY_DATA, "val", (64, 64), train_augment=False)
    assert len(data.deploy_val) == len(val) - 10
    assert torch.equal(data.deploy_val[0]["depth"], val[10]["depth"])
    assert torch.equal(data.deploy_val[len(val) - 11]["depth"], val[len(val) - 1]["depth"])
    assert tuple(data.train[0]["image"].shape[-2:]) == (32, 32)
    assert tuple(data.deploy_train[0]["image"].shape[-2:]) == (64, 64)


def test_a_start_past_the_validation_set_is_refused():
    context = SearchConfig(study="held-out", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    with pytest.raises(SystemExit, match="validation set has 16 frames"):
        held_out_data(context, seed=0, val_from=16)


def test_recipes_take_the_studys_tuning_unless_given():
    fixed = SearchConfig(study="s", tune_steps=20)
    assert parse_recipes("300, 2000+130", fixed) == {"300": (300, 20), "2000_tune130": (2000, 130)}
    assert parse_recipes("2000", fixed) == {"2000": (2000, 20)}
    assert parse_recipes("300+20", fixed) == {"300_tune20": (300, 20)}
    assert parse_recipes("2000", SearchConfig(study="s")) == {"2000": (2000, 133)}   # the default share


@pytest.mark.parametrize("text", ["", "300x", "300+", "0", "300+-1"])
def test_a_recipe_that_is_not_n_or_n_plus_t_is_refused(text):
    with pytest.raises(SystemExit, match="--steps"):
        parse_recipes(text, SearchConfig(study="s"))
