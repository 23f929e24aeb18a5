"""Reading the files a user hands the package, and writing files so that a reader never sees half of one.

Every reader turns what can go wrong with a user's file (missing, a folder, binary, too large, not
valid YAML or JSON, YAML aliases) into one :class:`~explorer.errors.UserError` line naming the file.
Every writer writes a scratch file beside the target and renames it into place (``os.replace`` is
atomic on one file system), so a process killed at any moment leaves the old file or the new one.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import yaml

from explorer.errors import UserError

#: the largest YAML or JSON file the package reads: spaces, profiles and manifests are kilobytes
MAX_TEXT_BYTES = 16 * 1024 * 1024


class _NoAliasLoader(yaml.SafeLoader):
    """PyYAML's safe loader without aliases: nested aliases expand exponentially (a file of a kilobyte
    can stand for gigabytes), and none of the package's files needs them."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.events.AliasEvent):
            mark = self.peek_event().start_mark
            raise yaml.composer.ComposerError(None, None, "YAML aliases (*name) are not supported here: "
                                              "write the values out", mark)
        return super().compose_node(parent, index)


def read_text(path: str | Path, what: str = "file") -> str:
    """The text of a user's file, or a UserError that says why not (missing, a folder, unreadable,
    larger than ``MAX_TEXT_BYTES``, binary)."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p}: is a folder, expected a {what}")
    try:
        with open(p, "rb") as f:
            raw = f.read(MAX_TEXT_BYTES + 1)
    except FileNotFoundError:
        raise UserError(f"{p}: no such file") from None
    except OSError as exc:
        raise UserError(f"{p}: cannot read the {what} ({exc.strerror})") from None
    if len(raw) > MAX_TEXT_BYTES:
        raise UserError(f"{p}: larger than {MAX_TEXT_BYTES // 2**20} MB: not a {what}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{p}: a binary file, not a {what} (expected UTF-8 text)") from None


def read_yaml(path: str | Path, what: str = "YAML file") -> Any:
    """A user's YAML file, parsed safely (no Python objects, no aliases)."""
    p = Path(path)
    text = read_text(p, what)
    try:
        return yaml.load(text, Loader=_NoAliasLoader)   # noqa: S506  (a SafeLoader without aliases)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise UserError(f"{p}: not valid YAML{where}: {problem}") from None


def read_json(path: str | Path, what: str = "JSON file") -> Any:
    """A user's JSON file, parsed (NaN and Infinity refused: no file of the package holds them)."""
    p = Path(path)
    text = read_text(p, what)

    def no_constants(name: str):
        raise ValueError(f"{name} is not a number JSON allows")

    try:
        return json.loads(text, parse_constant=no_constants)
    except (json.JSONDecodeError, ValueError) as exc:
        raise UserError(f"{p}: not valid JSON ({exc})") from None


def write_atomically(path: str | Path, data: "str | bytes") -> Path:
    """Writes ``data`` to ``path`` through a scratch file in the same folder, flushed to disk, then
    renamed into place: readers, and a process killed midway, see the old file or the new one."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".tmp{os.getpid()}", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def write_json(path: str | Path, data: Any, indent: int = 2) -> Path:
    """``write_atomically`` of ``data`` as JSON."""
    return write_atomically(path, json.dumps(data, indent=indent) + "\n")
