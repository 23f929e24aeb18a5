"""A study's journal file, synced to the disk once a trial's state changes rather than at every write.

Optuna's ``JournalFileBackend`` calls ``fsync`` after each write, and a trial writes a line per
parameter and attribute (about 35 in the default space): those waits for the disk weigh most where a
candidate is evaluated in tens of milliseconds (on a GPU). Every line is still
written and flushed under the journal's lock at once, so another process reads it at once and a
killed process loses nothing; what waits for the next trial state change is only the disk's copy,
which matters if the machine itself goes down (then the running trial's last lines may be lost, and
Optuna's reader skips a torn last line)."""

from __future__ import annotations

import json
import os
from typing import Any

from optuna.storages.journal import JournalFileBackend, JournalFileSymlinkLock

#: Optuna's journal operation code of a trial state change (``JournalOperation.SET_TRIAL_STATE_VALUES``)
#: and of a new study: the lines after which the file is synced
_SYNC_AFTER = {0, 6}


class TrialSyncedJournal(JournalFileBackend):
    """``JournalFileBackend`` that syncs the file after trial state changes and study creation only."""

    def __init__(self, path: str) -> None:
        lock = JournalFileSymlinkLock(path)   # the lock Optuna takes by default
        super().__init__(path, lock_obj=lock)
        self._path, self._file_lock = path, lock

    def append_logs(self, logs: list[dict[str, Any]]) -> None:
        text = "".join(json.dumps(log, separators=(",", ":")) + "\n" for log in logs)
        sync = any(log.get("op_code") in _SYNC_AFTER for log in logs)
        self._file_lock.acquire()
        try:
            _cut_torn_tail(self._path)
            with open(self._path, "ab") as f:
                f.write(text.encode("utf-8"))
                f.flush()
                if sync:
                    os.fsync(f.fileno())
        finally:
            self._file_lock.release()


def _cut_torn_tail(path: str) -> None:
    """Removes a last line without its newline, the trace of a writer that died mid-write (a machine
    that went down): appended to, it would fuse with the next line into one that no reader can parse,
    and the study could not be opened again. Called under the journal's lock, where every writer writes
    whole lines, so such a tail is never a write in progress. The cut bytes are kept beside the journal
    (``.torn``); they are part of one operation of the trial that was running, which is tried again."""
    try:
        with open(path, "rb+") as f:
            size = f.seek(0, os.SEEK_END)
            if size == 0:
                return
            f.seek(size - 1)
            if f.read(1) == b"\n":
                return
            keep = size
            while keep > 0:   # back to the last newline, a block at a time
                start = max(keep - 65536, 0)
                f.seek(start)
                block = f.read(keep - start)
                cut = block.rfind(b"\n")
                if cut >= 0:
                    keep = start + cut + 1
                    break
                keep = start
            f.seek(keep)
            torn = f.read()
            with open(f"{path}.torn", "ab") as aside:
                aside.write(torn + b"\n")
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    except FileNotFoundError:
        return
