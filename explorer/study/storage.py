"""Optuna storage for studies: a journal file (Optuna's JournalStorage) for one or several processes on
one machine, PostgreSQL (or any RDB URL) for several machines; SQLite when asked for (or where a study
has its ``study.db``), never with several workers.

The journal is the default because a search reads its study far more often than it writes it (the
sampler, the duplicate check and the trial count read every trial, every trial): a journal is replayed
once into memory and then read from there, while SQLite answers each read with a query."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

import optuna

from explorer.errors import UserError
from explorer.study.retry import rdb_retry_kwargs

REPORTS_DIR = Path("reports")
# RDB storage (PostgreSQL): a running trial records a heartbeat every HEARTBEAT_S seconds; one silent
# for GRACE_S is failed by another worker (and tried again, see explorer.study.retry). Both can be set in
# the environment (ANYTIME_EXPLORER_HEARTBEAT_S, ANYTIME_EXPLORER_GRACE_S), e.g. short ones for tests.
HEARTBEAT_S, GRACE_S = 30, 120


def heartbeat_settings() -> tuple[int, int]:
    """(heartbeat interval, grace period) in whole seconds, from the environment or the defaults."""
    out = []
    for var, default in (("ANYTIME_EXPLORER_HEARTBEAT_S", HEARTBEAT_S), ("ANYTIME_EXPLORER_GRACE_S", GRACE_S)):
        text = os.environ.get(var, "").strip()
        try:
            value = int(text) if text else default
        except ValueError:
            raise UserError(f"{var}={text!r}: give a whole number of seconds") from None
        if value < 1:
            raise UserError(f"{var}={text!r}: give at least 1 second")
        out.append(value)
    return out[0], out[1]


#: a study name is a folder name and a database key: letters, digits, '-', '_' and '.', not first
STUDY_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")


def check_study_name(study: str) -> str:
    if not isinstance(study, str) or not STUDY_NAME.fullmatch(study):
        raise UserError(f"study name {study!r} must be a plain name: letters, digits, '-', '_' and '.', "
                        "starting with a letter or digit, at most 100 characters")
    return study


def study_dir(study: str, reports: Path = REPORTS_DIR) -> Path:
    return reports / check_study_name(study)


def _make_parent(path: Path, what: str) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{path.parent}: cannot create the folder for the {what} ({exc.strerror}): "
                        "give a --storage path you can write") from None


def _check_journal(path: Path) -> None:
    """A file given as a journal must be one: Optuna's journal is JSON, one operation a line."""
    if not path.exists() or path.stat().st_size == 0:
        return
    if path.is_dir():
        raise UserError(f"{path}: is a folder, not a study journal")
    with open(path, "rb") as f:
        first = f.readline(1 << 20)
    try:
        entry = json.loads(first)
    except (ValueError, UnicodeDecodeError):
        entry = None
    if not isinstance(entry, dict) or "op_code" not in entry:
        raise UserError(f"{path}: not an Optuna study journal (give the journal file explorer search wrote, "
                        "or a new path)")


def default_url(study: str, reports: Path = REPORTS_DIR) -> str:
    return f"sqlite:///{study_dir(study, reports) / 'study.db'}"


def journal_path(study: str, reports: Path = REPORTS_DIR) -> Path:
    return study_dir(study, reports) / "journal.log"


def local_url(study: str, reports: Path = REPORTS_DIR) -> str:
    """The storage URL of ``study`` on this machine: its journal file in reports/<study>/, or the
    SQLite database there when the study has one and no journal."""
    if not journal_path(study, reports).exists() and (study_dir(study, reports) / "study.db").exists():
        return default_url(study, reports)
    return f"journal:{journal_path(study, reports)}"


def open_storage(url: str | None, study: str, workers: int = 1, reports: Path = REPORTS_DIR,
                 create: bool = True, max_retries: int | None = None) -> optuna.storages.BaseStorage:
    """The storage for ``study``. ``url`` None: :func:`local_url`. A ``journal:PATH`` URL names a
    journal file explicitly. ``max_retries`` (searching workers): on RDB storage, a trial whose worker
    stopped is tried again that many times."""
    if url is None:
        url = local_url(study, reports)
    if url.startswith("sqlite") and workers > 1:
        raise UserError(f"SQLite ({url}) cannot take several workers safely: use --workers 1 with it, a "
                        "--storage journal:PATH on this machine, or --storage postgresql://... for several machines")
    if url.startswith("journal:"):
        path = Path(url[len("journal:"):])
        if not create and not path.exists():
            raise UserError(f"no study journal at {path} (run `explorer search --study {study}` first, "
                            "or give --storage)")
        _check_journal(path)
        _make_parent(path, "study journal")
        return _replayed_journal(path, study)
    if url.startswith("sqlite:///"):
        path = Path(url[len("sqlite:///"):])
        if not create and not path.exists():
            raise UserError(f"no study database at {path} (run `explorer search --study {study}` first, "
                            "or give --storage)")
        _make_parent(path, "study database")
    url = _with_driver(url)
    kwargs = {}
    if not url.startswith("sqlite"):
        # crashed workers' trials are failed by the others after the grace period, and retried
        interval, grace = heartbeat_settings()
        kwargs = {"heartbeat_interval": interval, "grace_period": grace, **rdb_retry_kwargs(max_retries, grace)}
    try:
        storage = _rdb_storage(url, kwargs)
    except Exception as exc:  # sqlalchemy raises many types for unreachable or malformed URLs
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        for secret in _passwords(url):
            first = first.replace(secret, "***")
        raise UserError(f"storage {redacted(url)}: unreachable or invalid ({first[:160]})") from None
    if create and url.startswith("sqlite:///") and not on_network_filesystem(Path(url[len("sqlite:///"):])):
        _write_ahead(storage)   # the search writes; readers leave the file's mode as they find it
    return storage


def _replayed_journal(path: Path, study: str) -> optuna.storages.JournalStorage:
    """The journal at ``path`` read into memory; a damaged line (edited by hand, a disk error) is one
    line naming it, and the file is left as it is."""
    from explorer.study._journal import TrialSyncedJournal, first_damage
    try:
        return optuna.storages.JournalStorage(TrialSyncedJournal(str(path)))
    except (ValueError, KeyError, TypeError, AssertionError, AttributeError, IndexError) as exc:
        damage = first_damage(str(path))
        what = (f"line {damage[0]} is damaged ({damage[1]})" if damage
                else f"cannot be replayed ({type(exc).__name__}: {str(exc)[:120]})")
        raise UserError(f"study '{study}': journal {path}: {what}; nothing was changed: restore the file from a "
                        "backup, or move that line out of it (keep a copy) to read the rest") from None


#: attempts at opening a database whose tables other workers may be creating at the same moment
TABLE_RACE_ATTEMPTS = 5


def _rdb_storage(url: str, kwargs: dict) -> optuna.storages.RDBStorage:
    """Optuna's RDBStorage for ``url``. Workers started together on an empty database all create its
    tables at once; on PostgreSQL all but one fail (a duplicate table or type). The tables are then
    there, so a worker that lost the race opens the database again, after a short random pause."""
    import random
    import time
    import warnings

    import sqlalchemy.exc
    attempt = 1
    while True:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(url, engine_kwargs={"pool_pre_ping": True}, **kwargs)
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
            if attempt == TABLE_RACE_ATTEMPTS:
                raise
            time.sleep(random.uniform(0.1, 0.5) * attempt)
            attempt += 1


#: file systems shared between machines, where SQLite's write-ahead log (shared memory) does not work
MOUNTS = Path("/proc/mounts")
NETWORK_FILESYSTEMS = ("nfs", "nfs4", "cifs", "smb3", "smbfs", "lustre", "gpfs", "beegfs", "ceph",
                       "glusterfs", "fuse.sshfs", "9p", "afs")


def on_network_filesystem(path: Path) -> bool:
    """Whether ``path`` lies on a network file system, by the longest mount point above it in
    /proc/mounts (False where that cannot be read)."""
    try:
        mounts = [line.split()[1:3] for line in MOUNTS.read_text().splitlines()]
    except OSError:
        return False
    target = str(path.resolve())
    best, kind = "", ""
    for point, fs in mounts:
        point = point.replace("\\040", " ")
        inside = target == point or target.startswith(point.rstrip("/") + "/")
        if inside and len(point) > len(best):
            best, kind = point, fs
    return kind in NETWORK_FILESYSTEMS


def _write_ahead(storage: optuna.storages.RDBStorage) -> None:
    """SQLite in write-ahead-log mode, synced at checkpoints rather than at every commit: Optuna
    commits once per parameter and attribute (about 30 a trial), and a sync each made storage cost
    more than a supernet estimate. A killed process loses nothing committed; a power cut may lose
    the last trials, never the database's consistency. At exit the file goes back to a rollback
    journal, so that it stays one self-contained file others can read from a read-only folder."""
    import atexit

    from sqlalchemy import event, text

    def pragmas(connection, _record) -> None:
        cursor = connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.close()

    def leave_one_file() -> None:
        storage.engine.dispose()   # leaving WAL mode needs the only connection
        try:
            with storage.engine.connect() as connection:
                connection.execute(text("PRAGMA journal_mode=DELETE"))
        except Exception:   # another process still has it open: it stays in WAL mode, readable all the same
            pass
        storage.engine.dispose()

    event.listen(storage.engine, "connect", pragmas)
    storage.engine.dispose()   # connections opened while the tables were made reconnect with the pragmas
    atexit.register(leave_one_file)


def _with_driver(url: str) -> str:
    """postgresql:// with whichever driver is installed (SQLAlchemy 2.1 defaults to psycopg 3)."""
    if url.startswith("postgresql://"):
        import importlib.util
        if importlib.util.find_spec("psycopg") is None:
            if importlib.util.find_spec("psycopg2") is None:
                raise UserError("PostgreSQL storage needs a driver: pip install 'anytime-explorer[postgres]'")
            return "postgresql+psycopg2://" + url[len("postgresql://"):]
    return url


def _local_file(url: str) -> Path | None:
    """The file of a journal or SQLite study URL; None for a database server."""
    for prefix in ("journal:", "sqlite:///"):
        if url.startswith(prefix):
            return Path(url[len(prefix):])
    return None


@contextlib.contextmanager
def searching_alone(url: str, study: str):
    """Holds the study's search lock on this machine while a search runs, for a journal or SQLite
    study: a second search started on the same study (another terminal) is refused in one line instead
    of failing the first one's running trial. Workers of one search (``--workers``) run under their
    parent's lock; PostgreSQL studies are shared by design (several machines) and take none. The lock
    file is removed when the search ends, however it ends (but kill -9)."""
    file = _local_file(url)
    if file is None:
        yield
        return
    file = file.resolve()   # one lock per study file, whatever path (symlink, relative) names it
    from explorer.files import check_writable_folder
    check_writable_folder(file.parent, "study's journal and lock", "give --reports or --storage a folder you can write")
    lock_path = file.with_name(f".{file.name}.search-lock")
    lock = _take_lock(lock_path, study)
    try:
        lock.seek(0)
        lock.truncate()
        with contextlib.suppress(OSError):   # who holds it, for the next search's refusal: a full disk locks too
            os.write(lock.fileno(), f"process {os.getpid()}".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            lock_path.unlink()    # still held: a search that opened it meanwhile finds it gone and retries
        lock.close()              # and with it the lock


def _take_lock(lock_path: Path, study: str):
    """``lock_path`` opened and locked; a held lock is one line. A file unlinked by the search that held
    it, between our open and our lock, is opened again."""
    import fcntl
    while True:
        try:
            lock = open(lock_path, "a+")
        except OSError as exc:
            raise UserError(f"{lock_path}: cannot write the study's lock file ({exc.strerror}): "
                            "give a --storage or --reports folder you can write") from None
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            lock.close()
            raise UserError(f"study '{study}' is being searched by {holder} on this machine: wait for it to end, "
                            "or stop it and resume (one search with --workers N samples in parallel)") from None
        try:
            same = os.stat(lock_path).st_ino == os.fstat(lock.fileno()).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return lock
        lock.close()


@contextlib.contextmanager
def refused_leaves_nothing(url: str, study: str):
    """A search refused (a UserError) before any of its trials ran leaves its storage as it found it: a
    journal is cut back to its size before (where only this process wrote to it since), a journal or
    database it created is removed, with the folders it made for it where they are empty."""
    file = _local_file(url)
    if file is None:
        yield
        return
    existed, journal = file.exists(), url.startswith("journal:")
    size = file.stat().st_size if existed and journal and file.is_file() else 0
    made = [folder for folder in file.parents if not folder.exists()]   # the folders a search would make
    try:
        yield
    except UserError:
        if file.is_file():
            _undo(file, journal, existed, size, url, study)
        for folder in made:   # innermost first, each only if empty
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def _undo(file: Path, journal: bool, existed: bool, size: int, url: str, study: str) -> None:
    from explorer.study._journal import undo_own_appends
    undone = undo_own_appends(str(file), size) if journal else not existed and not _has_run(url, study)
    if undone and not existed:
        for leftover in (file, Path(f"{file}-wal"), Path(f"{file}-shm"), Path(f"{file}.torn")):
            leftover.unlink(missing_ok=True)


def _has_run(url: str, study: str) -> bool:
    """Whether ``study`` at ``url`` holds a trial that ran (or runs), or cannot be read (then kept)."""
    try:
        storage = open_storage(url, study, create=False)
        names = [s.study_name for s in optuna.get_all_study_summaries(storage)]
        if names and names != [study]:
            return True
        if not names:
            return False
        ran = optuna.load_study(study_name=study, storage=storage).get_trials(
            deepcopy=False, states=[s for s in optuna.trial.TrialState if s != optuna.trial.TrialState.WAITING])
        return bool(ran)
    except Exception:   # unreadable: keep it
        return True


def find_storage(study: str, url: str | None, reports: Path = REPORTS_DIR) -> optuna.storages.BaseStorage:
    """The storage of an existing study (for report, rescore, export)."""
    return open_storage(url or local_url(study, reports), study, create=False)


def load_study(study: str, url: str | None = None, reports: Path = REPORTS_DIR) -> optuna.Study:
    storage = find_storage(study, url, reports)
    try:
        return optuna.load_study(study_name=study, storage=storage)
    except KeyError:
        names = [s.study_name for s in optuna.get_all_study_summaries(storage)]
        raise UserError(f"no study named '{study}' in that storage (it has: {names or 'none'})") from None


_SCHEME = re.compile(r"^[a-z0-9+.-]+://", re.IGNORECASE)
#: a password given as a query parameter (libpq takes ?password=...)
_QUERY_PASSWORD = re.compile(r"(?<![^&])((?:password|passwd)=)([^&#]*)", re.IGNORECASE)


def _parts(url: str) -> tuple[str, str, str, str, str] | None:
    """(scheme://, user, password, host and path, query) of a URL with a scheme, else None. The user part
    ends at the last '@' before the query, so a password holding '/' or '@' is the password whole."""
    m = _SCHEME.match(url)
    if not m:
        return None
    base, _, query = url[m.end():].partition("?")
    userinfo, at, host = base.rpartition("@")
    if not at or userinfo.startswith("/") or ":" not in userinfo:   # no password (sqlite:///a:b@c.db)
        return m.group(0), "", "", base, query
    user, _, password = userinfo.partition(":")
    return m.group(0), user, password, host, query


def _passwords(url: str) -> list[str]:
    parts = _parts(url)
    if parts is None:
        return []
    return [p for p in (parts[2], *(v for _, v in _QUERY_PASSWORD.findall(parts[4]))) if p]


def redacted(url: str) -> str:
    """``url`` with its passwords, if any, written as ``***`` (user:PASSWORD@host, ?password=...): what
    may be printed or logged."""
    parts = _parts(url)
    if parts is None:
        return url
    scheme, user, password, host, query = parts
    base, mark, _ = url[len(scheme):].partition("?")
    if password:
        base = f"{user}:***@{host}"
    return scheme + base + mark + _QUERY_PASSWORD.sub(lambda m: f"{m.group(1)}***" if m.group(2) else m.group(0), query)
