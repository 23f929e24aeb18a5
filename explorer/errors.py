"""The one exception type a user can cause: printed as one line, exit status 2; and the writes a
machine refuses (a full disk, a read-only folder), told apart from the program's own errors so that
they are one line too, saying what was kept."""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from typing import Callable, Iterator


class UserError(Exception):
    """A mistake in the user's input (file, option, data). The message says what and how to fix it."""


#: the errors of a write that the machine refused, not the program: each with what frees it
REFUSED_WRITES = {
    errno.ENOSPC: "free space on that disk, or give a folder on another one",
    errno.EDQUOT: "free space within your disk quota, or give a folder on another disk",
    errno.EFBIG: "give a folder on a file system that holds larger files",
    errno.EROFS: "give a folder you can write",
    errno.EACCES: "give a path you can read and write",
    errno.EPERM: "give a path you can read and write",
}


def refused_write(exc: BaseException | None) -> OSError | None:
    """The ``OSError`` of a refused write (``REFUSED_WRITES``: a full disk or quota, a read-only file
    system, no permission) that ``exc`` is, or that it was raised while handling or because of: torch's
    checkpoint writer and Optuna raise an error of their own over it. None if there is none."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in REFUSED_WRITES:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


@contextmanager
def kept_if_refused(kept: Callable[[], str]) -> Iterator[None]:
    """A write refused in the block (``refused_write``) carries ``kept()``: what the command kept and how
    to go on, said in its one line (:func:`refused_line`). The innermost block that knows says it."""
    try:
        yield
    except Exception as exc:
        refused = refused_write(exc)
        if refused is not None and getattr(refused, "kept", None) is None:
            refused.kept = kept()
        raise


def refused_line(exc: OSError) -> str:
    """A refused write in one line: the file, why, what to do and what was kept. ``exc.filename`` names
    the file where the writer knew it (the atomic writers name their target, not their scratch)."""
    where = f"{exc.filename}: " if exc.filename else ""
    why = os.strerror(exc.errno).lower()
    if exc.errno not in (errno.EACCES, errno.EPERM):   # those may be a read's too
        why = f"cannot write it ({why})"
    kept = getattr(exc, "kept", None) or ("nothing is left half-written and what was saved before is kept: "
                                          "run the same command again")
    return f"{where}{why}: {REFUSED_WRITES[exc.errno]}; {kept}"
