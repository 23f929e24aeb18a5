"""A time limit that sizes the supernet's steps: the supernet trained is the one the plan sized, and
the study's estimates read it."""

import dataclasses

import optuna

from conftest import TINY_DATA
from explorer.data.synthetic import cache_dir
from explorer.space import SearchSpace
from explorer.study.planning import Plan, Speeds, TimeLimit
from explorer.study.records import study_record, trial_record
from explorer.study.search import SearchConfig, SearchRun, search
from explorer.supernet import default_path, read_supernet

CFG = SearchConfig(study="planned", space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64),
                   batch_size=8, val_limit=8, evaluator="supernet", supernet_steps=4, finalists=0, baselines=())


def test_the_supernet_trained_has_the_steps_the_plan_gave_it(tmp_path, monkeypatch):
    import explorer.study.search as search_module
    cache = tmp_path / "cache"        # no supernet cached: this study trains its own
    cache.mkdir()
    for data in cache_dir().glob("synthetic-*.h5"):   # the tests' data, not generated again
        (cache / data.name).symlink_to(data)
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(cache))
    plan = Plan(limit_s=600.0, supernet_steps=6, supernet_s=1.0, sampling_s=30.0, finalists=0, finalist_steps=5,
                retrain_jobs=0, retrain_s=0.0, changes=("supernet 6 steps",))

    def planned(context, storage, limit, sampling_s, on_data=None, clock=None):   # the machine measured: 6 steps fit
        return dataclasses.replace(context.config, supernet_steps=6), plan, Speeds(0.01, 0.1, 0.01)

    monkeypatch.setattr(search_module, "plan_search", planned)
    out = search(CFG.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path / "reports",
                                          time_limit=TimeLimit(600.0, free=frozenset({"supernet_steps"}))))
    space = SearchSpace.from_yaml(CFG.space)
    trained = default_path(space, CFG.data, dataclasses.replace(CFG, supernet_steps=6).supernet_recipe())
    assert study_record(out.study).supernet == str(trained.resolve())
    assert read_supernet(trained)["step"] == 6
    assert not default_path(space, CFG.data, CFG.supernet_recipe()).exists()   # not the recipe's 4 steps
    estimates = out.study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert estimates and all(trial_record(t).evaluator_name == "supernet" for t in estimates)


def _rewrite(file, **changes):
    import torch
    state = torch.load(file, map_location="cpu", weights_only=True)
    recipe = {**state["recipe"], **changes.pop("recipe", {})}
    torch.save({**state, "recipe": recipe, **changes}, file)


def test_a_winner_estimated_with_a_supernet_stopped_short_exports_until_the_supernet_trains_on(
        tmp_path, monkeypatch, run_cli):
    cache = tmp_path / "cache"
    cache.mkdir()
    for data in cache_dir().glob("synthetic-*.h5"):
        (cache / data.name).symlink_to(data)
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(cache))
    out = search(CFG.resolve(), SearchRun(n_trials=2, timeout_s=None, reports=tmp_path / "reports"))
    file = default_path(SearchSpace.from_yaml(CFG.space), CFG.data, CFG.supernet_recipe())
    assert all(trial_record(t).evaluator["supernet_step"] == 4 for t in out.study.get_trials()
               if trial_record(t).evaluator)
    # as a time limit leaves it: short of its recipe's steps, the weights the search estimated with
    _rewrite(file, recipe={"steps": 8}, complete=False)
    args = ("export", "--study", "planned", "--reports", tmp_path / "reports", "--eval-frames", 2)
    code, _, err = run_cli(*args, "--out", tmp_path / "short")
    assert code == 0, err
    assert (tmp_path / "short" / "manifest.json").is_file()
    _rewrite(file, step=6)     # a later study trained it on: its slice is another network now
    code, _, err = run_cli(*args, "--out", tmp_path / "later")
    assert code == 2 and "has trained on since (step 6)" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "later").exists()
