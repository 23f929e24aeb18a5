"""Where a study lives: a journal file by default; SQLite (write-ahead log while a search writes, one
plain file after) when asked for or where the study has its database."""

import sqlite3
import subprocess
import sys
from pathlib import Path

import optuna
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
