"""``explorer search --sampler``: which Optuna sampler proposes a study's candidates."""

import optuna
import pytest

from explorer.cli import build_parser
from explorer.cli.study import _search_context
from explorer.errors import UserError
from explorer.study.config import SAMPLERS, SearchConfig
from explorer.study.records import study_record
from explorer.study.sampling import RecentTrialsTPE
from explorer.study.search import create_or_resume, make_sampler


def _study(*flags: str) -> optuna.Study:
    """The study ``explorer search FLAGS`` creates (in memory: nothing is trained)."""
    context = _search_context(build_parser().parse_args(["search", "--study", "sampler-test", *flags]))
    return create_or_resume(context, optuna.storages.InMemoryStorage())


def test_sampler_random_makes_a_study_sample_uniformly():
    study = _study("--sampler", "random")
    assert isinstance(study.sampler, optuna.samplers.RandomSampler)
    assert study_record(study).config["sampler"] == "random"   # a resumed study reads it back


def test_the_default_sampler_is_tpe():
    assert isinstance(_study().sampler, RecentTrialsTPE)


def test_random_stays_random_with_several_objectives_and_in_every_worker():
    config = SearchConfig(study="s", sampler="random", objectives=("anytime_loss", "params"))
    assert isinstance(make_sampler(config, worker=2), optuna.samplers.RandomSampler)
    assert isinstance(make_sampler(SearchConfig(study="s", objectives=("anytime_loss", "params"))),
                      optuna.samplers.NSGAIISampler)


def test_the_flag_offers_the_samplers_the_config_accepts():
    action = next(a for a in build_parser()._subparsers._group_actions[0].choices["search"]._actions
                  if "--sampler" in a.option_strings)
    assert tuple(action.choices) == SAMPLERS and action.default == "tpe"


def test_an_unknown_sampler_is_one_line():
    with pytest.raises(UserError, match="--sampler cmaes"):
        SearchConfig(study="s", sampler="cmaes").validate()
