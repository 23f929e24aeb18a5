"""Faults of a study's journal and its lock (issue 89): every write is in the file at once (another
process reads it), and the disk is synced after trial state changes, not after every parameter; a torn
last line is cut before the next write, a whole one without its newline is kept, a damaged line anywhere
is one line naming it; a killed search loses no committed trial, and its interrupted trial is retried
whatever the storage URL; a second search (or an envelope) on a study being searched is refused, the lock
taken on the real file; a refused search writes nothing and leaves no lock."""

import os
import subprocess
import sys

import optuna
import pytest

from explorer.study import _journal, storage
from explorer.study._journal import TrialSyncedJournal
from _faults import fast_search, files as all_files, sqlite_url


def test_every_line_is_readable_at_once_and_syncs_wait_for_a_trial_state_change(tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(_journal.os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    path = str(tmp_path / "study.log")
    study = optuna.create_study(study_name="s", storage=optuna.storages.JournalStorage(TrialSyncedJournal(path)))
    after_create = len(synced)
    assert after_create == 1
    trial = study.ask()
    for i in range(5):
        trial.suggest_int(f"x{i}", 0, 9)
    trial.set_user_attr("note", "kept")
    assert len(synced) == after_create            # parameters and attributes: written, not synced
    reader = optuna.load_study(study_name="s", storage=optuna.storages.JournalStorage(TrialSyncedJournal(path)))
    seen = reader.trials[0]
    assert len(seen.params) == 5 and seen.user_attrs == {"note": "kept"}   # already in the file
    study.tell(trial, 1.0)
    assert len(synced) == after_create + 1       # the trial's end is on the disk
    reread = optuna.load_study(study_name="s", storage=optuna.storages.JournalStorage(TrialSyncedJournal(path)))
    assert reread.best_value == 1.0 and reread.trials[0].state == optuna.trial.TrialState.COMPLETE


def test_a_torn_last_line_is_cut_before_the_next_write_and_the_study_reads_again(tmp_path):
    """A machine that went down mid-write leaves a last line without its newline: the next write must not
    fuse with it into a line no reader can parse (the study would be lost for good)."""
    path = tmp_path / "study.log"
    storage = lambda: optuna.storages.JournalStorage(TrialSyncedJournal(str(path)))  # noqa: E731
    study = optuna.create_study(study_name="s", storage=storage())
    for value in (1.0, 2.0):
        trial = study.ask()
        trial.suggest_int("x", 0, 9)
        study.tell(trial, value)
    whole = path.read_bytes()
    path.write_bytes(whole[:-40])                         # the last operation torn
    resumed = optuna.load_study(study_name="s", storage=storage())
    trial = resumed.ask()
    trial.suggest_int("x", 0, 9)
    resumed.tell(trial, 0.5)
    again = optuna.load_study(study_name="s", storage=storage())
    assert again.best_value == 0.5 and len(again.trials) == 3
    assert path.read_bytes().count(b"\n") == len(path.read_bytes().splitlines())   # whole lines only
    assert (tmp_path / "study.log.torn").read_bytes().strip() == whole[:-40][whole[:-40].rfind(b"\n") + 1:]


def _two_trials(path) -> None:
    study = optuna.create_study(study_name="s", storage=optuna.storages.JournalStorage(TrialSyncedJournal(str(path))))
    for value in (1.0, 2.0):
        trial = study.ask()
        trial.suggest_int("x", 0, 9)
        trial.set_user_attr("note", value)
        study.tell(trial, value)


def test_a_whole_last_line_without_its_newline_is_read_and_kept(tmp_path):
    path = tmp_path / "study.log"
    _two_trials(path)
    path.write_bytes(path.read_bytes().rstrip(b"\n"))     # the second trial's end, whole, no newline
    storage = lambda: optuna.storages.JournalStorage(TrialSyncedJournal(str(path)))  # noqa: E731
    study = optuna.load_study(study_name="s", storage=storage())
    assert [t.value for t in study.trials] == [1.0, 2.0]
    trial = study.ask()
    trial.suggest_int("x", 0, 9)
    study.tell(trial, 0.5)
    again = optuna.load_study(study_name="s", storage=storage())
    assert [t.value for t in again.trials] == [1.0, 2.0, 0.5]
    assert not (tmp_path / "study.log.torn").exists()


def _damage(lines: list[bytes], how: str) -> list[bytes]:
    out = list(lines)
    if how == "not json":
        out[3] = b'{"op_code":8,"trial_id":0,"user_attr":{"note"\n'
    elif how == "two attributes":
        out[3] = out[3].replace(b'"user_attr":{', b'"user_attr":{"extra":1,')
    elif how == "no op_code":
        out[3] = out[3].replace(b'"op_code":8,', b"")
    return out


@pytest.mark.parametrize("how", ["not json", "two attributes", "no op_code"])
@pytest.mark.parametrize("command", ["search", "report", "rescore"])
def test_a_damaged_line_before_the_last_is_one_line_naming_it_and_nothing_is_written(tmp_path, run_cli, how, command):
    path = tmp_path / "study.log"
    _two_trials(path)
    path.write_bytes(b"".join(_damage(path.read_bytes().splitlines(keepends=True), how)))
    files = lambda: sorted(p.name for p in tmp_path.iterdir())  # noqa: E731
    before = files(), path.read_bytes()
    args = {"search": ["search", "--space", "tiny", "--trials", "1"],
            "report": ["report", "--out", tmp_path / "r.html"],
            "rescore": ["rescore", "--device", "tx2", "--budget", "time:uniform:33ms"]}[command]
    code, _, err = run_cli(*args, "--study", "s", "--storage", f"journal:{path}", "--reports", tmp_path)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "line 4 is damaged" in err and "'s'" in err
    assert (files(), path.read_bytes()) == before


@pytest.mark.slow
def test_a_killed_search_loses_no_committed_trial(tmp_path):
    script = ("import optuna, os, sys; from pathlib import Path; from explorer.study.storage import open_storage\n"
              "st = open_storage(None, 's', reports=Path(sys.argv[1]))\n"
              "study = optuna.create_study(storage=st, study_name='s')\n"
              "study.optimize(lambda t: t.suggest_int('x', 0, 9), n_trials=5)\n"
              "os.kill(os.getpid(), 9)\n")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True)
    assert done.returncode == -9
    study = optuna.load_study(study_name="s", storage=storage.open_storage(None, "s", reports=tmp_path))
    assert len(study.trials) == 5


@pytest.mark.parametrize("kind", ["journal", "sqlite"])
def test_a_second_search_on_a_study_being_searched_is_refused_and_touches_nothing(tmp_path, run_cli, kind):
    """Two terminals on one study: the second search says so in one line (exit 2) and leaves the first
    one's trials alone; once the first has ended, the study resumes as usual."""
    url = f"journal:{tmp_path / 'cc' / 'journal.log'}" if kind == "journal" else sqlite_url(tmp_path)
    args = fast_search(tmp_path, "--storage", url)
    with storage.searching_alone(url, "cc"):                 # the first search, still running
        code, _, err = run_cli(*args)
        assert code == 2 and "is being searched by process" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "cc" / "journal.log").exists() and not (tmp_path / "s" / "study.db").exists()
    code, _, err = run_cli(*args)
    assert code == 0, err


@pytest.mark.parametrize("kind", ["default", "journal", "sqlite"])
def test_a_search_refused_after_its_storage_opened_leaves_no_study_and_no_lock(tmp_path, run_cli, kind, monkeypatch):
    """A refusal that comes once the study would exist (here: no CUDA device) writes no create-study line:
    the journal, the database, the lock and the folders made for them are gone again."""
    import torch
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    storage_flag = {"default": [], "journal": ["--storage", f"journal:{tmp_path / 'x' / 'j.log'}"],
                    "sqlite": ["--storage", sqlite_url(tmp_path)]}[kind]
    code, _, err = run_cli(*fast_search(tmp_path, "--accelerator", "cuda", *storage_flag))
    assert code == 2 and "cuda" in err and len(err.strip().splitlines()) == 1, err
    assert all_files(tmp_path) == []


def test_a_refused_search_on_an_existing_journal_appends_nothing_and_leaves_no_lock(tmp_path, run_cli, monkeypatch):
    import torch
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    journal = tmp_path / "other.log"
    optuna.create_study(study_name="other", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    before = journal.read_bytes()
    code, _, err = run_cli(*fast_search(tmp_path, "--accelerator", "cuda", "--storage", f"journal:{journal}"))
    assert code == 2, err
    assert all_files(tmp_path) == ["other.log"] and journal.read_bytes() == before


def test_a_search_leaves_no_lock_file_behind(tmp_path, run_cli):
    code, _, err = run_cli(*fast_search(tmp_path))
    assert code == 0, err
    assert not [p for p in tmp_path.rglob("*search-lock*")]


def test_the_search_lock_is_taken_on_the_real_file_whatever_path_names_it(tmp_path, run_cli):
    journal = tmp_path / "real" / "journal.log"
    journal.parent.mkdir()
    optuna.create_study(study_name="cc", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    (tmp_path / "link.log").symlink_to(journal)
    before = journal.read_bytes()
    with storage.searching_alone(f"journal:{journal}", "cc"):
        code, _, err = run_cli(*fast_search(tmp_path, "--storage", f"journal:{tmp_path / 'link.log'}"))
    assert code == 2 and "is being searched by process" in err, err
    assert journal.read_bytes() == before


def test_explorer_envelope_takes_the_study_lock_as_search_does(tmp_path, run_cli):
    journal = tmp_path / "j.log"
    optuna.create_study(study_name="cc", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    before = journal.read_bytes()
    with storage.searching_alone(f"journal:{journal}", "cc"):   # a search, or another envelope, running
        code, _, err = run_cli("envelope", "--study", "cc", "--storage", f"journal:{journal}", "--reports", tmp_path)
    assert code == 2 and "is being searched by process" in err and len(err.strip().splitlines()) == 1, err
    assert journal.read_bytes() == before


def test_a_trial_killed_on_an_explicit_journal_is_retried_on_resume(tmp_path, run_cli):
    journal = tmp_path / "explicit" / "j.log"
    code, _, err = run_cli(*fast_search(tmp_path, "--storage", f"journal:{journal}"))
    assert code == 0, err
    study = storage.load_study("cc", f"journal:{journal}")
    killed = study.ask()                      # a trial whose process was killed -9: RUNNING for ever
    killed.set_user_attr("candidate_key", "x")
    code, _, err = run_cli(*fast_search(tmp_path, "--storage", f"journal:{journal}", "--trials", "2"))
    assert code == 0, err
    states = {t.number: t.state for t in storage.load_study("cc", f"journal:{journal}").trials}
    assert states[killed.number] == optuna.trial.TrialState.FAIL
    assert optuna.trial.TrialState.RUNNING not in states.values()
