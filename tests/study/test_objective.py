"""The search's trial bookkeeping: a candidate proposed again finds the trial that evaluated it."""

import optuna
from optuna.distributions import FloatDistribution
from optuna.trial import TrialState, create_trial

from explorer.study.objective import FinishedTwins


def _trial(key, state=TrialState.COMPLETE, **attrs):
    return create_trial(state=state, params={"x": 0.0}, distributions={"x": FloatDistribution(0, 1)},
                        value=1.0 if state == TrialState.COMPLETE else None,
                        user_attrs={"candidate_key": key, "path_metrics": [], **attrs})


def test_the_first_evaluation_of_a_candidate_is_its_twin_and_new_trials_are_indexed_as_they_finish():
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study()
    twins = FinishedTwins()
    study.add_trials([_trial("a", baseline="paper"), _trial("a", finalist={"recipe": {}}), _trial("b")])
    assert twins.find(study, "a") is None                  # a baseline's or a finalist's run is not a twin
    assert twins.find(study, "b").number == 2
    study.add_trials([_trial("a"), _trial("a")])
    assert twins.find(study, "a").number == 3              # the first of the two, found once they finished
    assert twins.find(study, "c") is None


def test_an_earlier_trial_that_finished_later_becomes_the_twin():
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study()
    twins = FinishedTwins()
    first, second = study.ask(), study.ask()
    for trial in (first, second):
        trial.set_user_attr("candidate_key", "a")
        trial.set_user_attr("path_metrics", [])
    study.tell(second, 1.0)
    assert twins.find(study, "a").number == second.number
    study.tell(first, 1.0)
    assert twins.find(study, "a").number == first.number
