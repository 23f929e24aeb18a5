"""Where a study lives: a journal file by default; SQLite (write-ahead log while a search writes, one
plain file after) when asked for or where the study has its database."""

import sqlite3
import subprocess
import sys
from pathlib import Path

import optuna
import pytest
from sqlalchemy import text

from conftest import POSTGRES, needs_postgres
from explorer.study import storage


def _journal_mode(storage_obj) -> str:
    with storage_obj.engine.connect() as connection:
        return connection.execute(text("PRAGMA journal_mode")).scalar()


def _sqlite(tmp_path) -> str:
    return f"sqlite:///{tmp_path / 's' / 'study.db'}"


def test_a_new_study_is_a_journal_file(tmp_path):
    st = storage.open_storage(None, "s", reports=tmp_path)
    optuna.create_study(storage=st, study_name="s").optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    assert isinstance(st, optuna.storages.JournalStorage)
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["journal.log"]
    assert len(storage.load_study("s", None, tmp_path).trials) == 2


def test_a_study_with_its_sqlite_database_stays_in_it(tmp_path):
    (tmp_path / "s").mkdir()
    optuna.create_study(storage=_sqlite(tmp_path), study_name="s").optimize(lambda t: t.suggest_int("x", 0, 9),
                                                                            n_trials=2)
    assert storage.local_url("s", tmp_path) == _sqlite(tmp_path)
    assert len(storage.load_study("s", None, tmp_path).trials) == 2
    assert not (tmp_path / "s" / "journal.log").exists()


def test_sqlite_writes_through_a_write_ahead_log(tmp_path):
    st = storage.open_storage(_sqlite(tmp_path), "s")
    optuna.create_study(storage=st, study_name="s").optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    assert _journal_mode(st) == "wal"


def test_readers_leave_the_mode_as_they_find_it(tmp_path):
    db = tmp_path / "s" / "study.db"
    db.parent.mkdir()
    optuna.create_study(storage=f"sqlite:///{db}", study_name="s")
    reader = storage.open_storage(f"sqlite:///{db}", "s", create=False)
    assert _journal_mode(reader) == "delete"


def test_on_a_network_filesystem_the_database_keeps_its_rollback_journal(tmp_path, monkeypatch):
    mounts = tmp_path / "mounts"
    mounts.write_text(f"server:/export {tmp_path} nfs4 rw 0 0\n/dev/vda / ext4 rw 0 0\n")
    monkeypatch.setattr(storage, "MOUNTS", mounts)
    assert storage.on_network_filesystem(tmp_path / "s" / "study.db")
    assert not storage.on_network_filesystem(Path("/var/lib/x.db"))
    st = storage.open_storage(_sqlite(tmp_path), "s")
    optuna.create_study(storage=st, study_name="s")
    assert _journal_mode(st) == "delete"


def test_mounts_that_cannot_be_read_count_as_local(tmp_path, monkeypatch):
    monkeypatch.setattr(storage, "MOUNTS", tmp_path / "absent")
    assert not storage.on_network_filesystem(tmp_path)


def test_after_the_search_process_ends_the_sqlite_study_is_one_file(tmp_path):
    script = ("import optuna, sys; from pathlib import Path; from explorer.study.storage import open_storage\n"
              "st = open_storage(f'sqlite:///{sys.argv[1]}/s/study.db', 's')\n"
              "optuna.create_study(storage=st, study_name='s').optimize(lambda t: t.suggest_int('x', 0, 9), n_trials=3)\n")
    subprocess.run([sys.executable, "-c", script, str(tmp_path)], check=True, capture_output=True)
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["study.db"]
    with sqlite3.connect(tmp_path / "s" / "study.db") as connection:
        assert connection.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    study = optuna.load_study(study_name="s", storage=f"sqlite:///{tmp_path / 's' / 'study.db'}")
    assert len(study.trials) == 3


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
    from conftest import TINY_DATA
    url = f"journal:{tmp_path / 'cc' / 'journal.log'}" if kind == "journal" else _sqlite(tmp_path)
    args = ["search", "--study", "cc", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32",
            "--input-size", "32x32", "--evaluator", "proxy", "--proxy-steps", "2", "--batch-size", "8",
            "--no-baselines", "--finalists", "0", "--trials", "1", "--timeout", "0", "--no-report",
            "--reports", tmp_path, "--storage", url]
    with storage.searching_alone(url, "cc"):                 # the first search, still running
        code, _, err = run_cli(*args)
        assert code == 2 and "is being searched by process" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "cc" / "journal.log").exists() and not (tmp_path / "s" / "study.db").exists()
    code, _, err = run_cli(*args)
    assert code == 0, err


@needs_postgres
def test_workers_started_together_on_an_empty_postgres_database_all_open_it():
    """They all create Optuna's tables at once; without a second try, all but one failed (3 of 4 here)."""
    import uuid

    import psycopg2
    name = f"explorer_race_{uuid.uuid4().hex[:8]}"
    admin = psycopg2.connect(POSTGRES.rsplit("/", 1)[0] + "/postgres")
    admin.autocommit = True
    admin.cursor().execute(f"CREATE DATABASE {name}")
    try:
        url = POSTGRES.rsplit("/", 1)[0] + "/" + name
        code = f"from explorer.study.storage import open_storage; open_storage({url!r}, 's')"
        workers = [subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True) for _ in range(4)]
        errors = [w.communicate(timeout=120)[1] for w in workers]
        assert [w.returncode for w in workers] == [0] * 4, errors
    finally:
        admin.cursor().execute(f"DROP DATABASE {name} WITH (FORCE)")
        admin.close()


def test_an_unreachable_storage_is_named_without_its_password(run_cli, tmp_path):
    code, out, err = run_cli("search", "--study", "leak", "--reports", tmp_path, "--trials", "1",
                             "--storage", "postgresql://root:S3cretPw@127.0.0.1:5999/x")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "unreachable" in err
    assert "S3cretPw" not in err + out and "root:***@127.0.0.1:5999" in err
    assert storage.redacted("postgresql://u@h/x") == "postgresql://u@h/x"
    assert storage.redacted("journal:reports/x/journal.log") == "journal:reports/x/journal.log"


def _fast_search(tmp_path, *extra):
    from conftest import TINY_DATA
    return ["search", "--study", "cc", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32",
            "--input-size", "32x32", "--evaluator", "proxy", "--proxy-steps", "2", "--batch-size", "8",
            "--no-baselines", "--finalists", "0", "--trials", "1", "--timeout", "0", "--no-report",
            "--reports", tmp_path, *extra]


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("kind", ["default", "journal", "sqlite"])
def test_a_search_refused_after_its_storage_opened_leaves_no_study_and_no_lock(tmp_path, run_cli, kind, monkeypatch):
    """A refusal that comes once the study would exist (here: no CUDA device) writes no create-study line:
    the journal, the database, the lock and the folders made for them are gone again."""
    import torch
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    storage_flag = {"default": [], "journal": ["--storage", f"journal:{tmp_path / 'x' / 'j.log'}"],
                    "sqlite": ["--storage", _sqlite(tmp_path)]}[kind]
    code, _, err = run_cli(*_fast_search(tmp_path, "--accelerator", "cuda", *storage_flag))
    assert code == 2 and "cuda" in err and len(err.strip().splitlines()) == 1, err
    assert _files(tmp_path) == []


def test_a_refused_search_on_an_existing_journal_appends_nothing_and_leaves_no_lock(tmp_path, run_cli, monkeypatch):
    import torch
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    journal = tmp_path / "other.log"
    optuna.create_study(study_name="other", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    before = journal.read_bytes()
    code, _, err = run_cli(*_fast_search(tmp_path, "--accelerator", "cuda", "--storage", f"journal:{journal}"))
    assert code == 2, err
    assert _files(tmp_path) == ["other.log"] and journal.read_bytes() == before


def test_a_search_leaves_no_lock_file_behind(tmp_path, run_cli):
    code, _, err = run_cli(*_fast_search(tmp_path))
    assert code == 0, err
    assert not [p for p in tmp_path.rglob("*search-lock*")]


def test_a_damaged_stored_device_profile_is_refused_before_any_trial_runs(tmp_path, run_cli):
    from explorer.cli import build_parser
    from explorer.cli._common import resolve_data
    from explorer.cli.study import _search_context
    from explorer.study.search import create_or_resume
    args = build_parser().parse_args([str(a) for a in _fast_search(tmp_path)])
    resolve_data(args)
    study = create_or_resume(_search_context(args), storage.open_storage(None, "cc", reports=tmp_path))
    study.set_user_attr("device_profile", {**study.user_attrs["device_profile"], "body_exponent": 1e6})
    code, _, err = run_cli(*_fast_search(tmp_path))
    assert code == 2 and "body_exponent must lie in" in err and len(err.strip().splitlines()) == 1, err
    reread = storage.load_study("cc", reports=tmp_path)
    assert reread.trials == [] and not [p for p in tmp_path.rglob("*search-lock*")]


def test_the_search_lock_is_taken_on_the_real_file_whatever_path_names_it(tmp_path, run_cli):
    journal = tmp_path / "real" / "journal.log"
    journal.parent.mkdir()
    optuna.create_study(study_name="cc", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    (tmp_path / "link.log").symlink_to(journal)
    before = journal.read_bytes()
    with storage.searching_alone(f"journal:{journal}", "cc"):
        code, _, err = run_cli(*_fast_search(tmp_path, "--storage", f"journal:{tmp_path / 'link.log'}"))
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
    code, _, err = run_cli(*_fast_search(tmp_path, "--storage", f"journal:{journal}"))
    assert code == 0, err
    study = storage.load_study("cc", f"journal:{journal}")
    killed = study.ask()                      # a trial whose process was killed -9: RUNNING for ever
    killed.set_user_attr("candidate_key", "x")
    code, _, err = run_cli(*_fast_search(tmp_path, "--storage", f"journal:{journal}", "--trials", "2"))
    assert code == 0, err
    states = {t.number: t.state for t in storage.load_study("cc", f"journal:{journal}").trials}
    assert states[killed.number] == optuna.trial.TrialState.FAIL
    assert optuna.trial.TrialState.RUNNING not in states.values()


@pytest.mark.parametrize("url, shown", [
    ("postgresql://root:S3cretPw@127.0.0.1:5999/x", "postgresql://root:***@127.0.0.1:5999/x"),
    ("postgresql://root:S3cret/Pw@h/x", "postgresql://root:***@h/x"),           # a '/' in the password
    ("postgresql://root:S3cret@Pw@h/x", "postgresql://root:***@h/x"),           # an '@' in it
    ("postgresql://root@h/x?password=S3cretPw&sslmode=require", "postgresql://root@h/x?password=***&sslmode=require"),
    ("postgresql://h/x?user=root&PASSWORD=S3cretPw", "postgresql://h/x?user=root&PASSWORD=***"),
    ("mysql://root:S3cretPw@h:notaport/x", "mysql://root:***@h:notaport/x"),
    ("sqlite:///a:b@c.db", "sqlite:///a:b@c.db"),                               # a file name, no password
    ("postgresql://u:@h/x", "postgresql://u:@h/x"),
])
def test_a_storage_url_is_shown_with_every_password_masked(url, shown):
    assert storage.redacted(url) == shown and "S3cret" not in storage.redacted(url)
