"""The study journal: every write is in the file at once (another process reads it), and the disk is
synced after trial state changes, not after every parameter."""

import os

import optuna
import pytest

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
