"""A study's stored records: written through one schema, validated when read back."""

import math

import optuna
import pytest
from pydantic import ValidationError

from explorer.errors import UserError
from explorer.study.records import (
    RECORD_VERSION, VERSION_KEY, Measured, Retraining, record, record_study, record_values, study_record, trial_record,
)


def _study() -> optuna.Study:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study()


def test_a_live_trial_records_typed_fields_that_read_back_as_the_schema():
    study = _study()
    trial = study.ask()
    record(trial, candidate_key="k", params=[0, 10], path_metrics=[{"rmse": 0.5}, {"rmse": 0.4}],
           measured=Measured(data="synthetic", split="val", frames=8, input_size=(64, 64)))
    study.tell(trial, 0.4)
    rec = trial_record(study.trials[0])
    assert rec.candidate_key == "k" and rec.params == [0, 10] and rec.losses_of("rmse") == [0.5, 0.4]
    assert rec.measured.input_size == (64, 64) and rec.record_version == RECORD_VERSION
    assert study.trials[0].user_attrs["measured"] == {"data": "synthetic", "split": "val", "frames": 8,
                                                      "input_size": [64, 64]}   # plain JSON in Optuna's storage
    assert not rec.is_retrained and rec.figures == "estimate"


def test_writes_are_checked_against_the_schema():
    with pytest.raises(TypeError, match="not fields"):
        record_values(candidate_keys="typo")
    with pytest.raises(ValidationError):
        record_values(params="many")
    with pytest.raises(TypeError, match="not fields"):
        record_study(_study(), plans={})


def test_a_retraining_reads_as_measured_and_an_envelope_is_neither_estimate_nor_finalist():
    attrs = record_values(path_metrics=[{"rmse": 0.3}], workloads={}, finalist=Retraining(recipe={"steps": 5}))
    study = _study()
    study.add_trial(optuna.trial.create_trial(values=[0.3], user_attrs=attrs))
    study.add_trial(optuna.trial.create_trial(values=[0.3], user_attrs={**attrs, "finalist": None,
                                                                        "envelope": {"recipe": {}}}))
    fin, env = (trial_record(t) for t in study.trials)
    assert fin.is_retrained and fin.figures == "measured" and not fin.is_estimate
    assert env.is_envelope and not env.is_retrained and not env.is_estimate and env.figures == "measured"


@pytest.mark.parametrize("attrs, says", [
    ({"params": "lots"}, r"damaged \(params"),
    ({"finalist": {"estimate_trial": 3}}, r"damaged \(finalist\.recipe"),
    ({VERSION_KEY: RECORD_VERSION + 1}, "newer anytime-explorer"),
    ({VERSION_KEY: -1}, r"damaged \(record_version: -1"),
    ({VERSION_KEY: "1"}, r"damaged \(record_version"),
    ({"latency_ms": [0.0, float("nan")]}, r"damaged \(latency_ms holds nan"),
    ({"path_metrics": [{"rmse": float("inf")}]}, r"damaged \(path 0's rmse is inf"),
    ({"path_metrics": [{"rmse": -0.5}]}, r"damaged \(path 0's rmse is -0.5"),
])
def test_a_damaged_or_newer_record_is_one_line(attrs, says):
    study = _study()
    study.add_trial(optuna.trial.create_trial(values=[1.0], user_attrs=attrs))
    with pytest.raises(UserError, match=says) as caught:
        trial_record(study.trials[0])
    assert "\n" not in str(caught.value)


def test_the_study_record_holds_what_the_study_stored():
    study = _study()
    record_study(study, runs=[{"started": "now", "seconds": 3.0}], baselines_not_estimated={"x": "why"})
    stored = study_record(study)
    assert stored.runs[0]["seconds"] == 3.0 and stored.baselines_not_estimated == {"x": "why"}
    assert stored.config is None and stored.plan is None
    study.set_user_attr("runs", "not a list")
    with pytest.raises(UserError, match="damaged"):
        study_record(study)


def test_the_record_version_is_written_once_however_often_a_trial_records():
    study = _study()
    study.enqueue_trial({}, user_attrs=record_values(baseline="paper"))
    for expected in (0, 1):   # an enqueued baseline carries it already; a sampled trial writes it once
        trial, keys = study.ask(), []
        write = trial.set_user_attr
        trial.set_user_attr = lambda k, v, write=write: (keys.append(k), write(k, v))
        record(trial, candidate_key="k")
        record(trial, params=[0, 1])
        record(trial, losses={"uniform:0:10": 1.0})
        assert keys.count(VERSION_KEY) == expected and trial.user_attrs[VERSION_KEY] == RECORD_VERSION
        study.tell(trial, 1.0)


def test_a_completed_trial_with_a_nan_error_is_refused_where_its_metric_is_read():
    from explorer.study.results import trial_losses
    study = _study()
    nan = {"path_metrics": [{"rmse": 0.9, "photometric": 0.1}, {"rmse": float("nan"), "photometric": 0.2}]}
    study.add_trial(optuna.trial.create_trial(values=[1.0], user_attrs=nan))
    trial = study.trials[0]
    assert trial_losses(trial, "photometric") == [0.1, 0.2]    # NaN: a path not measured in that metric
    with pytest.raises(UserError, match=r"trial 0's stored record is damaged \(its per-path rmse"):
        trial_losses(trial, "rmse")
    study.add_trial(optuna.trial.create_trial(values=[1.0], user_attrs={"path_metrics": [{"rmse": float("nan")}] * 2}))
    assert all(math.isnan(x) for x in trial_losses(study.trials[1], "rmse"))   # no path measured: not an edit
