"""What the probe reads and writes: the bundle manifest and the results file, their format and
version, and the one error type the probe raises for a mistake the user can fix."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None

BUNDLE_FORMAT = "explorer-probe-bundle"
RESULTS_FORMAT = "explorer-probe-results"
VERSION = 1                       # of both the bundle layout and the results file
DEFAULT_PROVIDER = "CPUExecutionProvider"
WARMUP = 3


class ProbeError(Exception):
    """A mistake the user can fix: printed as one line, exit status 2."""



# -- the bundle manifest -------------------------------------------------------------------------
@dataclass(frozen=True)
class BundleManifest:
    """A bundle's ``manifest.json`` (the bundle manifest on the file formats page), typed: the probe has
    no pydantic, so a dataclass; this module names its keys (:func:`load_manifest` reads it,
    :func:`write_bundle_manifest` writes it). ``id``: a digest of the bundle's content, which results
    remember; ``repeats``: the timed runs per graph; ``input_size``: (H, W) of a candidate's inputs where its
    entry gives none; ``layers`` and ``candidates``: the graphs' entries as written (the file formats page
    lists their fields); ``written``: the whole manifest as written, which results keep under ``bundle``."""

    id: "str | None"
    repeats: "int | None"
    input_size: "tuple[int, int] | None"
    layers: list = field(default_factory=list)
    candidates: list = field(default_factory=list)
    written: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_json(cls, data: dict) -> "BundleManifest":
        size = data.get("input_size")
        return cls(id=data.get("id"), repeats=data.get("repeats"), input_size=tuple(size) if size else None,
                   layers=list(data.get("layers") or []), candidates=list(data.get("candidates") or []),
                   written=data)


def load_manifest(bundle_dir: Path) -> BundleManifest:
    """The manifest of the unpacked bundle in ``bundle_dir``, checked: this format and version, every
    graph it names inside the bundle."""
    path = Path(bundle_dir) / "manifest.json"
    try:
        data = json.loads(path.read_text())
    except OSError:
        raise ProbeError(f"{path}: no bundle manifest here (unpack the bundle and run probe.pyz inside it, "
                         "or pass --bundle DIR)") from None
    except json.JSONDecodeError:
        raise ProbeError(f"{path}: the bundle manifest is not valid JSON (unpack the bundle again)") from None
    if not isinstance(data, dict) or data.get("format") != BUNDLE_FORMAT or data.get("version") != VERSION:
        got = data if isinstance(data, dict) else {}
        raise ProbeError(f"{path}: bundle format {got.get('format')} v{got.get('version')}, this probe "
                         f"reads {BUNDLE_FORMAT} v{VERSION}: use the probe.pyz that came in the bundle")
    for name in _files_named(data):
        _check_inside(Path(bundle_dir), name, path)
    return BundleManifest.from_json(data)


def write_bundle_manifest(folder: Path, fields: dict, digest) -> BundleManifest:
    """Writes ``folder/manifest.json``: this format and version, ``fields`` (``explorer``, ``created``,
    ``scale``, ``seed``, ``input_size``, ``repeats``, ``layers``, ``candidates``) and the bundle's ``id``,
    ``digest`` (a hashlib object that has taken in every graph) updated with every field but ``created``."""
    data = {"format": BUNDLE_FORMAT, "version": VERSION, **fields}
    digest.update(json.dumps({k: v for k, v in data.items() if k != "created"}, sort_keys=True).encode())
    data["id"] = digest.hexdigest()[:16]
    (Path(folder) / "manifest.json").write_text(json.dumps(data, indent=1))
    return BundleManifest.from_json(data)


def _files_named(entry) -> list:
    """Every ``file`` value anywhere in a bundle manifest (layers, stages, checks, candidates' graphs)."""
    found, todo = [], [entry]
    while todo:
        item = todo.pop()
        if isinstance(item, dict):
            found += [v for k, v in item.items() if k == "file"]
            todo += [v for k, v in item.items() if k != "file"]
        elif isinstance(item, list):
            todo += item
    return found


def _check_inside(bundle_dir: Path, name, manifest_path: Path) -> None:
    """A graph the manifest names is a relative path inside the bundle: one that climbs out (``../``),
    is absolute or is no text would make the probe open a file outside it."""
    root = bundle_dir.resolve()
    inside = isinstance(name, str) and name and not Path(name).is_absolute()
    if inside:
        target = (root / name).resolve()
        inside = target == root or root in target.parents
    if not inside:
        raise ProbeError(f"{manifest_path}: graph file {name!r} lies outside the bundle (edited or hostile "
                         "manifest): unpack the bundle that explorer calibrate wrote again")


# -- results -------------------------------------------------------------------------------------
def read_results(path: Path) -> dict:
    """A results file, checked: whole JSON, this format and version."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ProbeError(f"{path}: cannot read results ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise ProbeError(f"{path}: not a whole results file (truncated or corrupt JSON): run the probe again "
                         "with another --out") from None
    if not isinstance(data, dict) or data.get("format") != RESULTS_FORMAT:
        raise ProbeError(f"{path}: not a probe results file (write one with `python3 probe.pyz --out FILE`)")
    if data.get("version") != VERSION:
        raise ProbeError(f"{path}: results of probe format v{data.get('version')}, this version reads v{VERSION}: "
                         "make a new bundle with `explorer calibrate --bundle` and probe again")
    for key in ("bundle", "device", "conditions", "layers", "stages"):
        if key not in data:
            raise ProbeError(f"{path}: results file lacks '{key}' (truncated or edited): run the probe again")
    return data


def write_atomically(path: Path, data: dict) -> None:
    """Whole file or the previous one, never half of one: an interrupt loses at most one graph."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)

