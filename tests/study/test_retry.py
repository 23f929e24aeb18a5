"""An interrupted trial (kill -9, Ctrl-C, a worker lost on PostgreSQL) is tried again with the same
candidate and attributes; a trial that fails by its own fault (NaN) is not; missing baselines are said."""

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import optuna
import pytest

from explorer.study.records import RECORD_VERSION, VERSION_KEY
from explorer.study.results import missing_baselines, trials_frame
from explorer.study.retry import (CTRL_C, RetryStaleTrials, counted_trials, enqueue_retry, guarded,
                            interrupted_trials)
from explorer.study.search import SearchConfig, SearchRun, objective_names, search
from explorer.study.view import study_view
from explorer.study.storage import load_study
from conftest import POSTGRES, TINY_DATA, journal_trials, needs_postgres

# proxy evaluator: the tiny space does not hold the paper design, so only proxy training runs it as a trial
TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=6,
            batch_size=8, val_limit=16, evaluator="proxy", finalists=0)
CLI_TINY = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size", "64x64",
            "--proxy-steps", "6", "--batch-size", "8", "--no-report", "--timeout", "0", "--evaluator", "proxy",
            "--finalists", "0"]


def _explorer(*args, env=None, **kw):
    return subprocess.Popen([sys.executable, "-m", "explorer", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})}, **kw)


def _running_trial(journal: Path, number: int) -> bool:
    """Trial ``number`` is RUNNING and has its candidate (parameters sampled, costed): killing it now
    interrupts it in training."""
    trials = journal_trials(journal, journal.parent.name)
    return len(trials) > number and trials[number].state.name == "RUNNING" and \
        "candidate_key" in trials[number].user_attrs


def _kill_when_running(proc, running, what: str) -> None:
    deadline = time.time() + 300
    while not running():
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"{what} never ran: {proc.communicate()}")
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _load(journal: Path, name: str) -> optuna.Study:
    return load_study(name, None, journal.parent.parent)


@pytest.mark.slow
def test_kill_9_during_the_paper_baseline_then_resume(tmp_path):
    db = tmp_path / "kp" / "journal.log"
    args = ["search", "--study", "kp", "--reports", tmp_path, "--trials", 4, *CLI_TINY]
    proc = _explorer(*args, start_new_session=True)
    _kill_when_running(proc, lambda: _running_trial(db, 0), "the paper baseline")
    assert _load(db, "kp").trials[0].state == optuna.trial.TrialState.RUNNING  # killed mid-trial

    resumed = _explorer(*args)
    out, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    study = _load(db, "kp")
    first, retry = study.trials[0], study.trials[3]
    assert first.state == optuna.trial.TrialState.FAIL and "interrupted" in first.system_attrs["fail_reason"]
    assert retry.state == optuna.trial.TrialState.COMPLETE
    assert retry.user_attrs["baseline"] == "paper" and retry.user_attrs["retry_of"] == 0
    assert retry.system_attrs["failed_trial"] == 0 and retry.system_attrs["retry_history"] == [0]  # Optuna's
    assert "trial 0 (paper design) was interrupted: tried again as trial 3" in err
    assert "ratio to the paper-design baseline" in out and "missing" not in out
    # the interrupted trial does not count toward --trials: 4 counted, 5 in all
    assert counted_trials(study) == 4 and len(study.trials) == 5
    assert study.metric_names == ["anytime_loss[time:uniform:33ms]"]
    frame = trials_frame(study).set_index("number")
    assert "tried again as trial 3" in frame.loc[0, "reason"] and frame.loc[3, "retry_of"] == 0


@pytest.mark.slow
def test_kill_9_during_a_sampled_trial_retries_it_once(tmp_path):
    db = tmp_path / "ks" / "journal.log"
    # tiny candidates train fast: more steps keep the kill inside the trial
    args = ["search", "--study", "ks", "--reports", tmp_path, "--trials", 3, "--no-baselines", *CLI_TINY,
            "--proxy-steps", 40]
    proc = _explorer(*args, start_new_session=True)
    _kill_when_running(proc, lambda: _running_trial(db, 1), "the second trial")
    killed = _load(db, "ks").trials[1]
    assert killed.state == optuna.trial.TrialState.RUNNING and killed.params

    resumed = _explorer(*args)
    _, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    study = _load(db, "ks")
    retries = [t for t in study.trials if "retry_of" in t.user_attrs]
    assert len(retries) == 1 and retries[0].user_attrs["retry_of"] == 1
    retry = retries[0]
    assert retry.number == 2  # enqueued on resume, so run first
    assert retry.params == killed.params and retry.user_attrs["candidate_key"] == killed.user_attrs["candidate_key"]
    assert retry.state == optuna.trial.TrialState.COMPLETE
    assert study.trials[1].state == optuna.trial.TrialState.FAIL
    # not counted twice: 3 counted toward --trials, the interrupted one on top
    assert counted_trials(study) == 3 and len(study.trials) == 4

    again = _explorer(*args)  # a finished study: nothing retried twice, nothing run
    _, err = again.communicate(timeout=600)
    assert again.returncode == 0, err
    assert len(_load(db, "ks").trials) == 4 and "tried again" not in err


def test_a_trial_failing_with_nan_is_not_retried(tmp_path):
    cfg = SearchConfig(study="nan", baselines=False, lr=1e30, **TINY)  # diverges: NaN loss at once
    out = search(cfg.resolve(), SearchRun(n_trials=2, timeout_s=None, reports=tmp_path))
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    trials = out.study.get_trials()
    assert len(trials) == 3 and all(t.state == optuna.trial.TrialState.FAIL for t in trials)
    assert all("FloatingPointError" in t.system_attrs["fail_reason"] for t in trials)
    assert not out.retried and not any("retry_of" in t.user_attrs for t in trials)
    assert interrupted_trials(out.study) == {} and counted_trials(out.study) == 3


def _study_with(trials: list, **config) -> optuna.Study:
    study = optuna.create_study()
    study.set_user_attr("config", {"baselines": True, **config})
    for t in trials:
        study.add_trial(t)
    return study


def test_ctrl_c_is_an_interruption_an_error_is_not():
    study = optuna.create_study()
    study.enqueue_trial({"x": 0.25}, user_attrs={"baseline": "paper"})

    def stopped(trial):
        trial.suggest_float("x", 0, 1)
        trial.set_user_attr("path_metrics", [{"rmse": 1.0}])   # a result of the stopped run: not carried over
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        study.optimize(guarded(stopped, max_retries=2))
    first, retry = study.trials
    assert first.state == optuna.trial.TrialState.FAIL and first.system_attrs["fail_reason"] == CTRL_C
    assert retry.state == optuna.trial.TrialState.WAITING and retry.params == {"x": 0.25}
    assert retry.user_attrs == {"baseline": "paper", "retry_of": 0, VERSION_KEY: RECORD_VERSION}
    assert counted_trials(study) == 0

    def broken(trial):
        trial.suggest_float("x", 0, 1)
        raise ValueError("bad candidate")

    study.optimize(guarded(broken, max_retries=2), n_trials=1, catch=(ValueError,))
    assert study.trials[1].state == optuna.trial.TrialState.FAIL        # the retry ran (same x) ...
    assert study.trials[1].params == {"x": 0.25}
    assert study.trials[1].system_attrs["fail_reason"] == "ValueError: bad candidate"
    assert len(study.trials) == 2 and counted_trials(study) == 1          # ... and failing is a result


def test_of_two_trials_asked_at_once_past_the_limit_the_later_is_not_run():
    """Two workers finish together, both see room for one more trial and both ask one: whichever looks
    first, the earlier-numbered trial runs and the later one is given back without any work."""
    study = optuna.create_study()
    study.enqueue_trial({"x": 0.5}, user_attrs={"baseline": "paper"})
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)     # one of two trials done
    ran = []

    def objective(trial):
        ran.append(trial.number)
        return trial.suggest_float("x", 0, 1)

    early, late = study.ask(), study.ask()                                   # the two workers' asks
    study.enqueue_trial({"x": 0.75}, user_attrs={"baseline": "paper"})
    queued = study.ask()                                                     # a third worker pops a baseline
    run = guarded(objective, max_retries=2, n_trials=2)
    for trial in (late, queued, early):                                      # the later asks look first
        try:
            study.tell(trial, run(trial))
        except optuna.TrialPruned:
            study.tell(trial, state=optuna.trial.TrialState.PRUNED)
    assert ran == [early.number] and counted_trials(study) == 2
    states = {t.number: t.state for t in study.trials}
    assert states[late.number] == states[queued.number] == optuna.trial.TrialState.PRUNED
    assert "not run" in study.trials[late.number].user_attrs["not_run"]
    assert "not run" in trials_frame(study).set_index("number").loc[late.number, "reason"]
    again = [t for t in study.trials if t.state == optuna.trial.TrialState.WAITING]
    assert [(t.system_attrs["fixed_params"], t.user_attrs["baseline"]) for t in again] == [({"x": 0.75}, "paper")]
    study.optimize(objective, n_trials=1)                                    # a longer search runs it
    assert ran[-1] == again[0].number and study.trials[again[0].number].params == {"x": 0.75}
    assert counted_trials(study) == 3


def test_retries_stop_after_max_retries():
    study = optuna.create_study()
    dist = {"x": optuna.distributions.FloatDistribution(0, 1)}
    study.add_trial(optuna.trial.create_trial(state=optuna.trial.TrialState.FAIL, params={"x": 0.5},
                                              distributions=dist, system_attrs={"fail_reason": CTRL_C}))
    numbers = [0]
    for _ in range(3):
        t = study.trials[numbers[-1]]
        new = enqueue_retry(study, t, max_retries=2)
        if new is None:
            break
        numbers.append(new)
        trial = study.ask()                      # the retry runs and is interrupted again
        assert trial.number == new and trial.params == {"x": 0.5}
        study._storage.set_trial_system_attr(trial._trial_id, "fail_reason", CTRL_C)
        study.tell(trial, state=optuna.trial.TrialState.FAIL)
    assert numbers == [0, 1, 2]                  # the first attempt and 2 retries
    assert study.trials[2].system_attrs["retry_history"] == [0, 1]


def test_a_stale_trial_on_rdb_is_marked_and_retried():
    study = optuna.create_study()
    study.add_trial(optuna.trial.create_trial(state=optuna.trial.TrialState.FAIL,
                                              user_attrs={"baseline": "fastdepth"}))
    RetryStaleTrials(max_retries=2, grace_period_s=120)(study, study.trials[0])
    assert "no heartbeat for 120 s" in interrupted_trials(study)[0]
    assert study.trials[1].user_attrs == {"baseline": "fastdepth", "retry_of": 0, VERSION_KEY: RECORD_VERSION}
    assert counted_trials(study) == 0


def test_missing_baselines_say_why(tmp_path, capsys):
    FAIL, WAITING = optuna.trial.TrialState.FAIL, optuna.trial.TrialState.WAITING
    study = _study_with([
        optuna.trial.create_trial(state=FAIL, user_attrs={"baseline": "paper"},
                                  system_attrs={"fail_reason": "FloatingPointError: training loss became nan"}),
        optuna.trial.create_trial(state=FAIL, user_attrs={"baseline": "fastdepth"},
                                  system_attrs={"fail_reason": "interrupted (process killed)"}),
        optuna.trial.create_trial(state=WAITING, user_attrs={"baseline": "fastdepth", "retry_of": 1}),
    ], device="tx2", budgets=["time:uniform:33ms"])
    why = {m["name"]: m["why"] for m in missing_baselines(study_view(study))}
    assert why["paper"] == "failed in trial 0: FloatingPointError: training loss became nan"
    assert why["paper-nee"] == "not run: it is not in this study"
    assert why["fastdepth"].startswith("not run yet: queued as trial 2 (trial 1 was interrupted (process killed))")

    from explorer.cli import _print_outcome
    _print_outcome(study_view(study), SearchConfig(study="x"), "sqlite:///x.db", tmp_path, write_report=False)
    out = capsys.readouterr().out
    assert "baseline paper design missing: failed in trial 0" in out
    assert "baseline FastDepth-like missing: not run yet" in out

    from explorer.report import write_report
    html = write_report(study_view(study), tmp_path).read_text()
    assert "Not in this table" in html and "failed in trial 0: FloatingPointError" in html

    none = _study_with([], baselines=False)
    assert {m["why"] for m in missing_baselines(study_view(none))} == {"not run: the study was created with --no-baselines"}


def test_a_baseline_the_time_limit_left_untrained_says_so():
    from explorer.study.records import record_study
    study = _study_with([], device="tx2", budgets=["time:uniform:33ms"])
    record_study(study, baselines_not_estimated={"fastdepth": "outside the space 'anytime_depth'"})
    assert {m["name"]: m["why"] for m in missing_baselines(study_view(study))}["fastdepth"] == (
        "not estimated: outside the space 'anytime_depth'; not retrained yet (--finalists 0, or the study has not "
        "ended)")
    record_study(study, plan={"finalists": 3, "not_retrained": 1})
    why = {m["name"]: m["why"] for m in missing_baselines(study_view(study))}["fastdepth"]
    assert why == ("not estimated: outside the space 'anytime_depth'; not retrained: the time limit came first (run "
                   "the search again with a longer --time-limit: it resumes and retrains it)")


def test_objectives_are_named():
    assert objective_names(SearchConfig(study="x")) == ["anytime_loss[time:uniform:33ms]"]
    assert objective_names(SearchConfig(study="x", budgets=("energy:uniform:0.5J",),
                                        objectives=("anytime_loss", "params", "first_exit_ms"))) == \
        ["anytime_loss[energy:uniform:0.5J]", "params", "first_exit_ms"]


@pytest.mark.slow
@needs_postgres
def test_postgres_worker_killed_another_retries_after_grace_period(tmp_path):
    from explorer.study.storage import open_storage
    name = f"hb-{uuid.uuid4().hex[:8]}"
    env = {"ANYTIME_EXPLORER_HEARTBEAT_S": "1", "ANYTIME_EXPLORER_GRACE_S": "2"}
    args = ["search", "--study", name, "--storage", POSTGRES, "--reports", tmp_path, "--trials", 4, *CLI_TINY]
    storage = open_storage(POSTGRES, name)

    def paper_running() -> bool:
        try:
            t = optuna.load_study(study_name=name, storage=storage).trials
        except KeyError:
            return False
        return bool(t) and t[0].state == optuna.trial.TrialState.RUNNING and "candidate_key" in t[0].user_attrs

    try:
        worker = _explorer(*args, env=env, start_new_session=True)
        _kill_when_running(worker, paper_running, "the paper baseline")
        time.sleep(3)  # past the grace period: the killed worker's trial is stale
        other = _explorer(*args, env=env)
        out, err = other.communicate(timeout=600)
        assert other.returncode == 0, err
        study = optuna.load_study(study_name=name, storage=storage)
        assert study.trials[0].state == optuna.trial.TrialState.FAIL
        assert "no heartbeat" in interrupted_trials(study)[0]
        retry = next(t for t in study.trials if t.user_attrs.get("retry_of") == 0)
        assert retry.state == optuna.trial.TrialState.COMPLETE and retry.user_attrs["baseline"] == "paper"
        assert json.dumps(retry.system_attrs["retry_history"]) == "[0]"
        assert "ratio to the paper-design baseline" in out
        assert counted_trials(study) == 4 and len(study.trials) == 5
    finally:
        try:
            optuna.delete_study(study_name=name, storage=storage)
        except KeyError:
            pass
