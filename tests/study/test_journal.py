"""The study journal: every write is in the file at once (another process reads it), and the disk is
synced after trial state changes, not after every parameter."""

import os

import optuna

from explorer.study import _journal
from explorer.study._journal import TrialSyncedJournal


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
