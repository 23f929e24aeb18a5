import os
import signal
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TINY_DATA = "synthetic:48:16"
POSTGRES = "postgresql://postgres@127.0.0.1:5432/test"


def _postgres_ok() -> bool:
    try:
        import psycopg2
        psycopg2.connect(POSTGRES, connect_timeout=3).close()
        return True
    except Exception:
        return False


needs_postgres = pytest.mark.skipif(not _postgres_ok(), reason="PostgreSQL at 127.0.0.1:5432 is not reachable")


def pytest_configure(config):
    # A suite started in the background by a shell (`make test &`, nohup, some CI runners) inherits Ctrl-C
    # ignored, and so would every command a test starts: the tests of what Ctrl-C does need the commands to
    # receive it as a terminal's user would. A handler of this process becomes the default in a child.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    os.environ.setdefault("ANYTIME_EXPLORER_CACHE", str(Path(config.rootpath) / ".cache" / "test-data"))
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        # one of several pytest-xdist workers: PyTorch (imported later) and the commands the tests start
        # use this worker's share of the cores, not all of them each (threads waiting on each other's
        # cores at every kernel are many times slower)
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        share = max(1, cores // workers)
        os.environ.setdefault("OMP_NUM_THREADS", str(share))


@pytest.fixture(autouse=True)
def _no_waiting_for_a_calm_machine(monkeypatch):
    """Probes in tests time tiny graphs that jitter: they re-time what ran slow but do not wait
    (up to a minute) for the shared machine to calm down first."""
    from explorer.probe import timing
    monkeypatch.setattr(timing, "CALM_WAIT_S", 0.0)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED.is_dir():
        pytest.skip("../shared/data is absent (a fresh clone has no shared/ beside it)")
    return SHARED


@pytest.fixture
def run_cli(capsys):
    """Runs the CLI in-process; returns (exit code, stdout, stderr)."""
    from explorer.cli import main

    def run(*args: str):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse
            code = exc.code
        out, err = capsys.readouterr()
        return code, out, err
    return run


def journal_trials(path: Path, study: str) -> list:
    """The trials of ``study`` in the journal file at ``path`` as they stand now, read without a lock
    while a search may be writing it ([] before the study exists)."""
    import optuna
    from optuna.storages.journal import JournalFileBackend
    if not path.exists():
        return []
    try:
        storage = optuna.storages.JournalStorage(JournalFileBackend(str(path)))
        return optuna.load_study(study_name=study, storage=storage).trials
    except (KeyError, ValueError):   # not created yet, or a line being written
        return []
