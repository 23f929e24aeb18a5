"""A study's journal file, synced to the disk once a trial's state changes rather than at every write.

Optuna's ``JournalFileBackend`` calls ``fsync`` after each write, and a trial writes a line per
parameter and attribute (about 35 in the default space): those waits for the disk weigh most where a
candidate is evaluated in tens of milliseconds (on a GPU). Every line is still
written and flushed under the journal's lock at once, so another process reads it at once and a
killed process loses nothing; what waits for the next trial state change is only the disk's copy,
which matters if the machine itself goes down (then the running trial's last lines may be lost, and
Optuna's reader skips a torn last line).

A last line that is whole but lacks its newline (a file edited by hand, copied by a tool that drops it)
is read and kept: only a line that is not a whole operation is torn. A damaged line before the last
is found by :func:`first_damage`, for a one-line refusal that names it."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from optuna.storages.journal import JournalFileBackend, JournalFileSymlinkLock

#: Optuna's journal operation code of a trial state change (``JournalOperation.SET_TRIAL_STATE_VALUES``)
#: and of a new study: the lines after which the file is synced
_SYNC_AFTER = {0, 6}
#: what this process appended to each journal (by its real path): (start, end, whether a trial ran in it)
_APPENDS: dict[str, list[tuple[int, int, bool]]] = {}
#: Optuna's TrialState.WAITING: an enqueued trial, which has not run
_WAITING = 4


def _runs_a_trial(log: dict[str, Any]) -> bool:
    """Whether a journal operation starts, ends or changes a trial's run (not an enqueued trial)."""
    op = log.get("op_code")
    return op == 6 or (op == 4 and log.get("state") != _WAITING)


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
                start = f.seek(0, os.SEEK_END)
                f.write(text.encode("utf-8"))
                f.flush()
                if sync:
                    os.fsync(f.fileno())
                ran = any(_runs_a_trial(log) for log in logs)
                _APPENDS.setdefault(os.path.realpath(self._path), []).append((start, f.tell(), ran))
        except OSError as exc:   # a full disk: the line names the journal (a torn line is cut by the next write)
            exc.filename = exc.filename or self._path
            raise
        finally:
            self._file_lock.release()

    def read_logs(self, log_number_from: int):
        """Optuna's reader, plus a last line that is a whole operation without its newline (Optuna's
        skips it until the next write completes it)."""
        count = 0
        for log in super().read_logs(log_number_from):
            count += 1
            yield log
        offset = self._log_number_offset.get(log_number_from + count)
        if offset is None:
            return
        with open(self._path, "rb") as f:
            f.seek(offset)
            tail = f.read()
        entry = whole_entry(tail) if tail and b"\n" not in tail else None
        if entry is not None:
            yield entry


def undo_own_appends(path: str, size: int) -> bool:
    """Cuts the journal at ``path`` back to ``size`` bytes where everything after is what this process
    appended since and no trial ran in it (a search refused after its study was created writes nothing).
    False, and the file left as it is, where another process wrote after ``size`` or a trial ran."""
    own = sorted(r for r in _APPENDS.get(os.path.realpath(path), []) if r[0] >= size)
    if not own:   # nothing of ours to cut, and no lock to take (a read-only folder refused takes none)
        return os.path.getsize(path) == size
    lock = JournalFileSymlinkLock(path)
    lock.acquire()
    try:
        pos = size
        for start, end, ran in own:
            if start != pos or ran:
                return False
            pos = end
        with open(path, "rb+") as f:
            if f.seek(0, os.SEEK_END) != pos:
                return False
            if pos > size:
                f.truncate(size)
                f.flush()
                os.fsync(f.fileno())
        return True
    finally:
        lock.release()


def whole_entry(line: bytes) -> dict | None:
    """``line`` as a journal operation (a JSON object with an op_code), or None where it is not one."""
    try:
        entry = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        return None
    return entry if isinstance(entry, dict) and "op_code" in entry else None


#: operations that carry one attribute each (Optuna's replay asserts it): set study user/system attr,
#: set trial user/system attr, by op_code
_ONE_ATTRIBUTE = {2: "user_attr", 3: "system_attr", 8: "user_attr", 9: "system_attr"}
#: the largest op_code Optuna writes (``JournalOperation``)
_LAST_OP = 10


def _line_damage(line: bytes) -> str | None:
    """What is wrong with one whole journal line, or None where it reads as an operation."""
    try:
        entry = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        return "not JSON"
    if not isinstance(entry, dict):
        return "not a JSON object"
    op = entry.get("op_code")
    if not isinstance(op, int) or isinstance(op, bool) or not 0 <= op <= _LAST_OP:
        return "no valid op_code" if op is None else f"unknown op_code {op!r}"
    key = _ONE_ATTRIBUTE.get(op)
    if key is not None and (not isinstance(entry.get(key), dict) or len(entry[key]) != 1):
        return f"op_code {op} must set exactly one attribute ({key})"
    return None


def first_damage(path: str) -> tuple[int, str] | None:
    """(line number from 1, what is wrong) of the first damaged line of the journal at ``path``, or None.
    A last line without its newline that is not whole is a torn write, repaired at the next write: not
    damage."""
    with open(path, "rb") as f:
        for number, line in enumerate(f, start=1):
            if not line.endswith(b"\n") and whole_entry(line) is None:
                return None
            reason = _line_damage(line)
            if reason is not None:
                return number, reason
    return None


def _cut_torn_tail(path: str) -> None:
    """Removes a last line without its newline, the trace of a writer that died mid-write (a machine
    that went down): appended to, it would fuse with the next line into one that no reader can parse,
    and the study could not be opened again. Called under the journal's lock, where every writer writes
    whole lines, so such a tail is never a write in progress. The cut bytes are kept beside the journal
    (``.torn``); they are part of one operation of the trial that was running, which is tried again.
    A tail that is a whole operation only lacks its newline: it gets one and is kept."""
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
            if whole_entry(torn) is not None:
                f.seek(0, os.SEEK_END)
                f.write(b"\n")
                f.flush()
                os.fsync(f.fileno())
                return
            aside_path = Path(f"{path}.torn")
            try:
                with open(aside_path, "ab") as aside:
                    aside.write(torn + b"\n")
            except OSError:   # a full disk: the tail stays until a write has room; no empty .torn is left
                if aside_path.is_file() and aside_path.stat().st_size == 0:
                    aside_path.unlink()
                raise
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    except FileNotFoundError:
        return
