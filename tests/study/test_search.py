import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import optuna
import pytest

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.errors import UserError
from explorer.study.results import rescore, scored_trials, trials_frame
from explorer.study.search import SearchConfig, SearchRun, search
from explorer.study.storage import load_study
from explorer.space import Candidate
from explorer.study.records import trial_record
from conftest import POSTGRES, TINY_DATA, journal_trials, needs_postgres

# These tests exercise storage, workers and resume with the proxy evaluator (tests/test_supernet.py
# covers the supernet evaluator, tests/test_finalists.py the end of a study).
TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=6,
            batch_size=8, val_limit=16, evaluator="proxy", finalists=0)
CLI_TINY = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size", "64x64",
            "--proxy-steps", "6", "--batch-size", "8", "--no-report", "--evaluator", "proxy", "--finalists", "0"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    reports = tmp_path_factory.mktemp("reports")
    cfg = SearchConfig(study="tiny-e2e", budgets=("time:uniform:30ms", "energy:uniform:0.5J"), **TINY)
    out = search(cfg.resolve(), SearchRun(n_trials=7, timeout_s=None, reports=reports))
    return out, reports


@pytest.mark.slow
def test_tiny_search_end_to_end(finished):
    out, reports = finished
    frame = trials_frame(out.study)
    assert len(frame) == 7
    assert list(frame["baseline"][:3]) == ["paper", "paper-nee", "fastdepth"]
    assert (frame["state"] == "COMPLETE").sum() >= 4
    t = scored_trials(out.study)[0]
    for key in ("candidate", "path_metrics", "workloads", "latency_ms", "energy_j", "params", "macs", "losses"):
        assert key in t.user_attrs
    assert set(t.user_attrs["losses"]) == {"time:uniform:30ms", "energy:uniform:0.5J"}
    assert (reports / "tiny-e2e" / "journal.log").is_file()   # the default storage of a study
    assert any((reports / "tiny-e2e" / "artifacts").iterdir())


def test_rescore_equals_direct_computation(finished):
    out, _ = finished
    frame = rescore(out.study, "rpi4", ["time:uniform:100ms", "energy:uniform:0.25J"])
    rpi4 = get_device("rpi4")
    for t in scored_trials(out.study):
        cand = Candidate.from_dict(trial_record(t).shipped_candidate)   # the network as it ships
        cost = candidate_cost(cand, (64, 64))
        losses = [m["rmse"] for m in t.user_attrs["path_metrics"]]
        direct = anytime_loss(cost.path_costs(rpi4, "time"), losses, "time:uniform:100ms")
        rows = frame[frame["number"] == t.number]
        if rows.empty:   # a network is listed once: by its measured (retrained) row, else its first estimate
            same_network = (frame["candidate_key"] == t.user_attrs["candidate_key"]) & \
                (frame["baseline"] == t.user_attrs.get("baseline", ""))
            assert same_network.sum() == 1
            continue
        row = rows.iloc[0]
        assert row["time:uniform:100ms"] == pytest.approx(direct, rel=1e-9)
        direct_e = anytime_loss(cost.path_costs(rpi4, "energy"), losses, "energy:uniform:0.25J")
        assert row["energy:uniform:0.25J"] == pytest.approx(direct_e, rel=1e-9)
    # what was measured first, then the estimates, each ranked; no network twice
    assert list(frame["figures"]) == sorted(frame["figures"], key=lambda kind: kind != "measured")
    for _, part in frame.groupby("figures"):
        assert part["time:uniform:100ms"].is_monotonic_increasing
    assert not frame.duplicated(["candidate_key", "baseline"]).any()
    # re-scoring on the study's own device and budget gives back the stored objective
    same = rescore(out.study, "tx2", ["time:uniform:30ms"]).set_index("number")
    for t in scored_trials(out.study):
        if t.number in same.index:
            assert same.loc[t.number, "time:uniform:30ms"] == pytest.approx(t.values[0])


def test_resume_with_other_settings_is_refused(finished):
    _, reports = finished
    cfg = SearchConfig(study="tiny-e2e", device="rpi4", **TINY)
    with pytest.raises(UserError, match="rescore"):
        search(cfg.resolve(), SearchRun(n_trials=1, reports=reports))


def test_constraints_reject_before_training(tmp_path):
    cfg = SearchConfig(study="constrained", baselines=False, max_params=1000, **TINY)
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    trials = out.study.get_trials()
    assert all(t.state == optuna.trial.TrialState.PRUNED for t in trials)
    assert all("--max-params" in t.user_attrs["rejected"] and "path_metrics" not in t.user_attrs for t in trials)


def test_multi_objective(tmp_path):
    cfg = SearchConfig(study="mo", baselines=False, objectives=("anytime_loss", "params"), **TINY)
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    assert len(out.study.directions) == 2
    assert out.study.metric_names == ["anytime_loss[time:uniform:33ms]", "params"]  # named for dashboards
    assert all(len(t.values) == 2 for t in out.study.get_trials() if t.values)


def test_sqlite_with_workers_refused(tmp_path, run_cli):
    code, _, err = run_cli("search", "--study", "x", "--workers", "2", "--storage",
                           f"sqlite:///{tmp_path}/x.db", "--reports", tmp_path, *CLI_TINY)
    assert code == 2 and "SQLite" in err


def _explorer(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "explorer", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _states(journal: Path) -> list[str]:
    return [t.state.name for t in journal_trials(journal, journal.parent.name)]


@pytest.mark.slow
def test_kill_9_then_resume(tmp_path):
    db = tmp_path / "killed" / "journal.log"
    proc = _explorer("search", "--study", "killed", "--reports", tmp_path, "--trials", "50",
                     "--timeout", "0", *CLI_TINY, start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline:
        states = _states(db)
        if states.count("COMPLETE") >= 2 and states and states[-1] == "RUNNING":
            break
        time.sleep(0.2)
    else:
        proc.kill()
        pytest.fail(f"search did not get going: {proc.communicate()}")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = _states(db)
    complete_before = before.count("COMPLETE")
    resumed = _explorer("search", "--study", "killed", "--reports", tmp_path,
                        "--trials", str(len(before) + 1), "--timeout", "0", *CLI_TINY)
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    after = _states(db)
    assert after.count("COMPLETE") >= complete_before          # nothing finished was lost
    assert after[len(before) - 1] == "FAIL"                     # the interrupted trial
    assert "RUNNING" not in after
    study = load_study("killed", None, tmp_path)
    assert "interrupted" in study.trials[len(before) - 1].system_attrs["fail_reason"]
    assert [t.user_attrs.get("retry_of") for t in study.trials].count(len(before) - 1) == 1  # tried again




@pytest.mark.slow
@needs_postgres
def test_three_workers_on_postgres(tmp_path):
    study = f"pg-{uuid.uuid4().hex[:8]}"
    total = 9
    procs = [_explorer("search", "--study", study, "--storage", POSTGRES, "--reports", tmp_path,
                       "--trials", total, "--timeout", "0", *CLI_TINY) for _ in range(3)]
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    from explorer.study.storage import open_storage
    storage = open_storage(POSTGRES, study)
    s = optuna.load_study(study_name=study, storage=storage)
    trials = s.get_trials()
    numbers = [t.number for t in trials]
    assert len(numbers) == len(set(numbers))                      # nothing duplicated
    assert all(t.state.is_finished() for t in trials)             # nothing lost mid-way
    finished = [t for t in trials if t.state.is_finished()]
    assert total <= len(finished) <= total + 2                    # at most one extra per other worker
    assert [t.user_attrs.get("baseline") for t in trials].count("paper") == 1
    assert len({t.user_attrs.get("candidate_key") for t in trials if t.user_attrs.get("baseline")}) == 3
    optuna.delete_study(study_name=study, storage=storage)


def test_a_candidate_sampled_twice_is_not_trained_twice(tmp_path):
    from explorer.space import SearchSpace
    cfg = SearchConfig(study="dup", baselines=False, **TINY)
    space = SearchSpace.from_yaml("tiny")
    cand = list(space.enumerate())[0]
    out = search(cfg.resolve(), SearchRun(n_trials=1, timeout_s=None, reports=tmp_path))
    out.study.enqueue_trial(space.params_of(cand))
    out.study.enqueue_trial(space.params_of(cand))
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    a, b = out.study.trials[1], out.study.trials[2]
    assert a.user_attrs["candidate_key"] == b.user_attrs["candidate_key"] == cand.key
    assert "duplicate_of" in b.user_attrs and b.values == a.values
    assert "path_metrics" in b.user_attrs  # re-scoring still sees it


@pytest.mark.slow
def test_two_workers_on_a_journal_file(tmp_path):
    cfg = SearchConfig(study="journal", **TINY)
    out = search(cfg.resolve(), SearchRun(workers=2, n_trials=6, timeout_s=None, reports=tmp_path))
    assert out.storage_url.startswith("journal:") and (tmp_path / "journal" / "journal.log").is_file()
    trials = out.study.get_trials()
    assert len({t.number for t in trials}) == len(trials) >= 6
    assert all(t.state.is_finished() for t in trials)
    from explorer.study.retry import counted_trials
    assert counted_trials(out.study) == 6          # the workers stop together, not one trial each past it
    assert [t.user_attrs.get("baseline") for t in trials].count("paper") == 1
