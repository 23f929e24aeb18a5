"""Reading the files a user hands the package, and writing files so that a reader never sees half of one.

Every reader turns what can go wrong with a user's file (missing, a folder, binary, too large, not
valid YAML or JSON, YAML aliases) into one :class:`~explorer.errors.UserError` line naming the file.
Every writer writes a scratch file beside the target and renames it into place (``os.replace`` is
atomic on one file system), so a process killed at any moment leaves the old file or the new one.
A folder (an export) is written whole in a scratch folder and swapped in; what a killed process left
beside it (named with its pid) is cleaned, or restored, by the next writer.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import yaml

from explorer.errors import UserError, refused_write
# scratch folders named by pid, cleaned when their process is gone; SIGTERM that unwinds (the probe
# holds them: it ships alone, and may import nothing of the package)
from explorer.probe.scratch import (process_alive, remove_own_scratch, remove_stale_scratch,  # noqa: F401
                                    scratch_dir, sigterm_unwinds)

#: the largest YAML or JSON file the package reads: spaces, profiles and manifests are kilobytes
MAX_TEXT_BYTES = 16 * 1024 * 1024


#: the most nodes a YAML file may stand for once its aliases are expanded: a kilobyte of nested
#: aliases can otherwise stand for billions ("billion laughs"), which every reader would then walk
MAX_YAML_NODES = 200_000


def _expanded_nodes(node: yaml.Node, seen: dict[int, int]) -> int:
    """How many nodes ``node`` stands for with every alias expanded (shared nodes counted each time
    they are referenced, each computed once)."""
    key = id(node)
    if key not in seen:
        seen[key] = 1   # a node that contains itself counts once
        if isinstance(node, yaml.SequenceNode):
            seen[key] = 1 + sum(_expanded_nodes(n, seen) for n in node.value)
        elif isinstance(node, yaml.MappingNode):
            seen[key] = 1 + sum(_expanded_nodes(k, seen) + _expanded_nodes(v, seen) for k, v in node.value)
    return seen[key]


#: the deepest nesting of lists and mappings a YAML file may have: PyYAML builds nested nodes by
#: recursion, and a few thousand '[' exhaust Python's stack (the package's files nest a few levels)
MAX_YAML_DEPTH = 100


def _check_depth(text: str) -> None:
    """Refuses ``text`` nesting deeper than ``MAX_YAML_DEPTH``, from the parser's events (a loop, not a
    recursion)."""
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise yaml.YAMLError(f"lists and mappings nest more than {MAX_YAML_DEPTH} deep: flatten it")
        elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            depth -= 1


class _RepeatedKey(Exception):
    """A mapping gives one key twice (args: the key, the lines of both): YAML forbids it, and PyYAML
    would keep the last in silence."""


def _repeated_key(root: yaml.Node) -> tuple[str, int, int] | None:
    """The first key a mapping under ``root`` repeats, with the lines of both. Walks the composed nodes,
    not the constructed values: nothing is built, and a node an alias shares is visited once."""
    stack, seen = [root], set()
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            lines: dict = {}
            for key, value in node.value:
                # a merge key (<<) may override what it merges: that is YAML, not a repeat
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    line = key.start_mark.line + 1
                    if (key.tag, key.value) in lines:
                        return key.value, lines[(key.tag, key.value)], line
                    lines[(key.tag, key.value)] = line
                stack.extend((key, value))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
    return None


def _load_yaml(text: str):
    """PyYAML's safe loader, refusing a document whose aliases expand past ``MAX_YAML_NODES``, that
    nests deeper than ``MAX_YAML_DEPTH`` or that gives a key of a mapping twice (:class:`_RepeatedKey`)."""
    _check_depth(text)
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_nodes(node, {}) > MAX_YAML_NODES:
            raise yaml.YAMLError(f"its aliases expand to more than {MAX_YAML_NODES:,} values (nested *aliases): "
                                 "write the values out")
        twice = _repeated_key(node)
        if twice:
            raise _RepeatedKey(*twice)
        return loader.construct_document(node)
    finally:
        loader.dispose()


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


def open_image(path: Path):
    """An image file opened lazily (header read), or one UserError line: unreadable, not an image, or
    larger than Pillow's decompression-bomb limit (a header may claim 40000x40000 pixels)."""
    from PIL import Image   # Pillow only where an image is read
    try:
        return Image.open(path)
    except Image.DecompressionBombError:
        raise UserError(f"{path}: the image claims more pixels than any camera frame (a corrupt or "
                        "hostile header): use real frames") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: unreadable image ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})") from None


#: Pillow's modes of 16-bit (and 32-bit integer) single-channel images
WIDE_GREY = ("I;16", "I;16B", "I;16L", "I;16N", "I")


def read_image(path: Path, mode: str | None = None) -> np.ndarray:
    """The pixels of an image file (converted to ``mode`` if given), or one UserError line. A 16-bit
    grey image read as RGB is scaled from its 16-bit range (Pillow's own conversion clips it at 255,
    white)."""
    from PIL import Image
    with open_image(path) as im:
        try:
            if mode == "RGB" and im.mode in WIDE_GREY:
                grey = np.asarray(im).astype(np.float64).clip(0, 65535) / 65535.0 * 255.0
                return np.repeat(np.rint(grey).astype(np.uint8)[..., None], 3, axis=2)
            return np.asarray(im.convert(mode) if mode else im)
        except Image.DecompressionBombError:
            raise UserError(f"{path}: the image claims more pixels than any camera frame") from None
        except (OSError, ValueError, SyntaxError) as exc:
            raise UserError(f"{path}: unreadable image ({type(exc).__name__})") from None


def read_yaml(path: str | Path, what: str = "YAML file") -> Any:
    """A user's YAML file, parsed safely (no Python objects, no alias bombs)."""
    p = Path(path)
    return parse_yaml(read_text(p, what), str(p))


def parse_yaml(text: str, source: str) -> Any:
    """YAML ``text`` (a file's, or one a study stored) parsed as :func:`read_yaml` parses a file; what is
    not valid YAML is one UserError line naming ``source``."""
    try:
        return _load_yaml(text)
    except _RepeatedKey as exc:
        key, first, again = exc.args
        raise UserError(f"{source}: the key {key!r} is given twice (lines {first} and {again}); keep one") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark else ""
        problem = getattr(exc, "problem", None) or (str(exc).splitlines() or [type(exc).__name__])[0]
        raise UserError(f"{source}: not valid YAML{where}: {problem}") from None


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
    except RecursionError:
        raise UserError(f"{p}: not valid JSON (nested too deep)") from None


@contextmanager
def writing_atomically(path: str | Path, mode: str = "wb", buffering: int = -1) -> Iterator[Any]:
    """A file opened on a scratch name beside ``path`` (``.NAME.XXXX.tmpPID``), flushed to disk and
    renamed onto ``path`` when the block ends, removed when it raises: readers, and a process killed
    midway, see the old file or the new one. The file gets the mode a plain ``open`` would give it (0644
    under the usual umask): ``mkstemp`` makes its scratch private, and an export or a profile is often
    read by another user or a service. A write the disk refuses (full, read-only) names ``path``."""
    p = Path(path)
    tmp = None
    try:
        fd, tmp = _scratch_beside(p)
        with os.fdopen(fd, mode, buffering) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        _name_target(exc, p)
        raise


@contextmanager
def replacing_file(path: str | Path) -> Iterator[Path]:
    """:func:`writing_atomically` for a writer that opens the file itself by name: yields the scratch's
    path (``.NAME.XXXX.tmpPID``, made empty, to be opened for writing and closed within the block),
    flushed to disk and renamed onto ``path`` when the block ends, removed when it raises (an error or
    Ctrl-C): readers, and a process killed midway, never see half a file. (HDF5 files are written with
    :func:`writing_hdf5`: HDF5 crashes after a write that fails.)"""
    p = Path(path)
    tmp = None
    try:
        fd, tmp = _scratch_beside(p)
        os.close(fd)
        yield Path(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, p)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        _name_target(exc, p)
        raise


@contextmanager
def writing_hdf5(path: str | Path) -> Iterator["Hdf5Writer"]:
    """An HDF5 file written as :func:`writing_atomically` writes one (a scratch beside ``path``, renamed
    onto it when the block ends, removed when it raises). HDF5 (2.0) whose write failed crashes the
    process (a segmentation fault) when it closes the file, even at exit: here it writes through a file
    object that never fails it. A write the disk refuses (full, read-only) is held in memory instead and
    raised once HDF5 has closed the file; :meth:`Hdf5Writer.check` raises it at once, for a writer to
    stop at (after a frame) rather than render the rest for nothing."""
    import h5py
    with writing_atomically(path, "r+b", buffering=0) as raw:
        sink = _NeverFailing(raw)
        h5 = h5py.File(sink, "w")
        try:
            yield Hdf5Writer(h5, sink)
        finally:
            h5.close()
        sink.check()


class Hdf5Writer:
    """:func:`writing_hdf5`'s file: ``file`` is the open ``h5py.File``; :meth:`check` raises the write
    the disk refused so far, if one was."""

    def __init__(self, file, sink: "_NeverFailing") -> None:
        self.file, self._sink = file, sink

    def check(self) -> None:
        self._sink.check()


class _NeverFailing(io.RawIOBase):
    """A file (unbuffered, seekable) whose writes never fail: once the disk refuses one, it and every
    later write are held in memory (reads see them), and the error waits for :meth:`check`."""

    def __init__(self, raw) -> None:
        super().__init__()
        self.raw, self.pos, self.error = raw, 0, None
        self.held: list[tuple[int, bytes]] = []   # (offset, data) refused by the disk, in order

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self.pos}.get(whence)
        if base is None:   # from the end: the file's, or past it what is held
            base = max([self.raw.seek(0, os.SEEK_END)] + [at + len(data) for at, data in self.held])
        self.pos = base + offset
        return self.pos

    def write(self, data) -> int:
        data = bytes(data)
        if self.error is None:
            try:
                self.raw.seek(self.pos)
                view, done = memoryview(data), 0
                while done < len(data):
                    done += self.raw.write(view[done:])
            except OSError as exc:
                self.error = exc
        if self.error is not None:
            self.held.append((self.pos, data))
        self.pos += len(data)
        return len(data)

    def readinto(self, buffer) -> int:
        self.raw.seek(self.pos)
        n = self.raw.readinto(buffer) or 0
        for at, data in self.held:
            lo, hi = max(at, self.pos), min(at + len(data), self.pos + len(buffer))
            if lo < hi:
                buffer[lo - self.pos:hi - self.pos] = data[lo - at:hi - at]
                n = max(n, hi - self.pos)
        self.pos += n
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self.pos if size is None else size
        try:
            self.raw.truncate(size)
        except OSError as exc:
            self.error = self.error or exc
        self.held = [(at, data[:max(size - at, 0)]) for at, data in self.held if at < size]
        return size

    def flush(self) -> None:
        pass

    def check(self) -> None:
        if self.error is not None:
            raise self.error


def _name_target(exc: BaseException, target: Path) -> None:
    """A refused write in ``exc`` named by the file being written (not its scratch, nor nothing)."""
    refused = refused_write(exc)
    if refused is not None and (refused.filename is None or ".tmp" in str(refused.filename)):
        refused.filename = str(target)


def _scratch_beside(p: Path) -> tuple[int, str]:
    """A new scratch file beside ``p`` (its descriptor and name), with the mode a plain ``open`` gives."""
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".tmp{os.getpid()}", dir=p.parent)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
    except OSError:
        os.close(fd)
        os.unlink(tmp)
        raise
    return fd, tmp


def current_umask() -> int:
    """The process's umask (read by setting it, then putting it back)."""
    umask = os.umask(0o022)
    os.umask(umask)
    return umask


def check_writable_folder(folder: str | Path, what: str, fix: str, keep: bool = True) -> Path:
    """``folder`` made if absent and a file written there and removed again, before any work: a file in
    its place, a read-only folder or file system (even for root, whom permission bits do not stop), or
    /proc is one line naming ``what`` would be written and how to ``fix`` it. ``keep=False``, for a
    command that makes the folder itself when it writes: nothing is made; the nearest folder that exists
    is probed with a folder of a unique name, made and removed again, so that commands refused at the
    same time never remove each other's folders or leave one behind."""
    folder = Path(folder)
    existing = next(f for f in (folder, *folder.parents) if f.exists() or f == f.parent)
    if not existing.is_dir():
        raise UserError(f"{existing}: is a file, not a folder for the {what}: {fix}")
    try:
        if keep:
            folder.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=".explorer-write-check.", dir=folder)
            os.close(fd)
            os.unlink(probe)
        else:
            os.rmdir(tempfile.mkdtemp(prefix=".explorer-write-check.", dir=existing))
    except OSError as exc:
        raise UserError(f"{folder}: cannot write the {what} there ({exc.strerror}): {fix}") from None
    return folder


def refuse_overwriting_inputs(out: str | Path, flag: str, inputs: dict[str, str | Path | None]) -> None:
    """A :class:`UserError` where the file ``out`` (given by ``flag``) is one of the command's ``inputs``
    (flag: path): writing the output would destroy what the command reads."""
    out = Path(out)
    if not out.exists():
        return
    for name, given in inputs.items():
        if given is not None and Path(given).exists() and os.path.samefile(out, given):
            raise UserError(f"{flag} {out}: is the file given to {name}; write the output to another file")


def check_free_space(folder: str | Path, need: int, what: str, fix: str) -> None:
    """Refuses in one line, before any work, a ``folder`` whose disk has less than ``need`` bytes free for
    the ``what`` to be written there (``fix``: how to go on). A disk that fills later is the writer's to
    tell (:func:`writing_atomically`)."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return   # not known here: the write itself tells
    if free < need:
        raise UserError(f"{folder}: {_size(free)} free on its disk, and the {what} needs about {_size(need)}: {fix}")


def _size(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def write_atomically(path: str | Path, data: "str | bytes") -> Path:
    """Writes ``data`` to ``path`` through :func:`writing_atomically`."""
    with writing_atomically(path, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    return Path(path)


def write_json(path: str | Path, data: Any, indent: int = 2) -> Path:
    """``write_atomically`` of ``data`` as JSON."""
    return write_atomically(path, json.dumps(data, indent=indent) + "\n")


def _leftovers(target: Path) -> Iterator[tuple[Path, str, int]]:
    pattern = re.compile(rf"\.{re.escape(target.name)}\.(tmp|old)(\d+)")
    for p in target.parent.glob(f".{target.name}.*"):
        m = pattern.fullmatch(p.name)
        if m:
            yield p, m.group(1), int(m.group(2))


SCRATCH = re.compile(r".*\.tmp(\d+)")


def remove_dead_scratch(folder: str | Path, only_for: str | Path | None = None) -> list[Path]:
    """Removes the scratch files and folders (``NAME.tmpPID``) that processes no longer alive left in
    ``folder`` (a generation killed by SIGTERM or kill -9); returns what it removed. ``only_for``: a
    file whose writers' scratch alone is removed (``FILE.tmpPID``, ``.FILE.XXXX.tmpPID``), for a folder
    that is the user's (a checkpoint's): files of their own that look like scratch are never touched.
    Without it the whole folder is the project's own (a cache)."""
    removed = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    pattern = SCRATCH
    if only_for is not None:
        name = re.escape(Path(only_for).name)
        pattern = re.compile(rf"(?:{name}|\.{name}\.[^/]*)\.tmp(\d+)")
    for p in folder.iterdir():
        m = pattern.fullmatch(p.name)
        if m and not process_alive(int(m.group(1))):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def recover_folder(target: str | Path) -> None:
    """Cleans what a writer of ``target`` killed midway left beside it: its scratch folder is removed,
    and a previous version it had moved aside is put back if ``target`` is missing."""
    target = Path(target)
    for path, kind, pid in _leftovers(target):
        if process_alive(pid) and pid != os.getpid():
            continue
        if kind == "old" and not target.exists():
            os.rename(path, target)
        else:
            shutil.rmtree(path, ignore_errors=True)


@contextmanager
def replacing_folder(target: str | Path, marker: str) -> Iterator[Path]:
    """Yields a scratch folder beside ``target``; when the block ends without an error the scratch
    replaces ``target`` whole (an error leaves ``target`` as it was and removes the scratch).
    ``marker``: a file every folder this writer makes holds; an existing ``target`` without it (someone's
    own folder) is refused rather than replaced."""
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise UserError(f"{target}: is a file; give a folder to write into")
    if target.is_dir() and any(target.iterdir()) and not (target / marker).is_file():
        raise UserError(f"{target}: exists and holds other files (no {marker}): give a new or empty folder")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{target.parent}: cannot create the folder ({exc.strerror})") from None
    recover_folder(target)
    scratch = target.with_name(f".{target.name}.tmp{os.getpid()}")
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        scratch.mkdir(mode=0o777)   # as the umask allows, like any folder the user makes
    except OSError as exc:
        raise UserError(f"{target.parent}: cannot write there ({exc.strerror})") from None
    try:
        yield scratch
    except BaseException as exc:
        shutil.rmtree(scratch, ignore_errors=True)
        _name_target(exc, target)
        raise
    aside = target.with_name(f".{target.name}.old{os.getpid()}")
    if target.exists():
        os.rename(target, aside)   # a kill between these renames is undone by recover_folder
    os.rename(scratch, target)
    shutil.rmtree(aside, ignore_errors=True)


def read_choices(raw: Any, where: str, kind: type, allow_empty: bool = False) -> list:
    """A YAML list of choices (one value is a list of one) of ``kind``, checked: no repeats, no negative
    integers, positive numbers; one UserError line naming ``where`` otherwise."""
    if not isinstance(raw, list):
        raw = [raw]
    if not raw and not allow_empty:
        raise UserError(f"{where}: the list of choices is empty: give at least one value")
    out = []
    for v in raw:
        if kind is bool:
            if not isinstance(v, bool):
                raise UserError(f"{where}: {v!r} is not true/false")
        elif kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise UserError(f"{where}: {v!r} is not an integer")
            if v < 0:
                raise UserError(f"{where}: {v} must not be negative")
        elif kind is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
                raise UserError(f"{where}: {v!r} is not a positive number")
            v = float(v)
        elif not isinstance(v, kind):
            raise UserError(f"{where}: {v!r} is not a {kind.__name__}")
        out.append(v)
    if len(set(out)) != len(out):
        raise UserError(f"{where}: choices {raw} repeat a value")
    return out


def read_stage_choices(raw: Any, where: str) -> tuple[tuple[int, ...], ...]:
    if not isinstance(raw, list) or not raw:
        raise UserError(f"{where}: give one list of width choices per decoder stage, e.g. [[256, 512], [64, 128]]")
    stages = []
    for k, stage in enumerate(raw, start=1):
        choices = read_choices(stage, f"{where}[stage {k}]", int)
        if any(c < 1 for c in choices):
            raise UserError(f"{where}[stage {k}]: widths must be positive")
        stages.append(tuple(choices))
    return tuple(stages)
