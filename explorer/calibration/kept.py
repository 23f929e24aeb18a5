"""This machine's profile as ``explorer curve`` calibrates it, kept for the next call on the same
machine: one file per machine identity (as the probe records a machine: host, board, processor,
architecture, cores, onnxruntime, execution provider, threads) and kind of calibration (full, or
``--quick``'s third of the sweep), under the cache folder (``ANYTIME_EXPLORER_CACHE``, else
``~/.cache/anytime-explorer``)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

from explorer.cost.devices import DeviceProfile, get_device
from explorer.data.synthetic import cache_dir
from explorer.errors import UserError
from explorer.files import write_atomically
from explorer.probe import default_threads, device_identity

#: what makes two calibrations one machine's: fields of the probe's ``device_identity``
IDENTITY = ("host", "board", "cpu", "machine", "cores", "onnxruntime", "provider", "threads")
#: those a profile's ``provenance["conditions"]`` holds too (identity field -> conditions field),
#: checked when a kept profile is read back; the others are in its file's name only
IN_CONDITIONS = {"cpu": "processor", "machine": "machine", "cores": "cores", "onnxruntime": "onnxruntime",
                 "provider": "provider"}


def this_machine(provider: str) -> dict:
    """This machine's identity, as a calibration with ``provider`` and the default threads records it."""
    found = device_identity(provider, default_threads())
    return {key: found.get(key) for key in IDENTITY}


def kept_path(identity: dict, quick: bool) -> Path:
    """Where the profile of the machine ``identity`` is kept (``quick``: the quick calibration's)."""
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()[:12]
    host = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(identity.get("host") or "host"))[:40]
    return cache_dir() / "profiles" / f"{host}-{digest}{'-quick' if quick else ''}.yaml"


def same_machine(profile: DeviceProfile, identity: dict) -> bool:
    """Whether ``profile`` was calibrated on the machine ``identity`` by what it records of it."""
    cond = profile.provenance.get("conditions") or {}
    return all(str(cond.get(field)) == str(identity[key]) for key, field in IN_CONDITIONS.items())


def find_kept(provider: str, quick: bool) -> Path | None:
    """The kept profile of this machine that serves a calibration (``quick``: a full one first, else a
    quick one; otherwise a full one only), or None. A file that cannot be read or that records another
    machine serves nothing (the calibration then made replaces it)."""
    identity = this_machine(provider)
    for path in [kept_path(identity, False)] + ([kept_path(identity, True)] if quick else []):
        if not path.is_file():
            continue
        try:
            profile = get_device(path)
        except (UserError, OSError):
            continue
        if same_machine(profile, identity):
            return path
    return None


def keep_profile(profile: DeviceProfile, provider: str, quick: bool) -> Path:
    """Writes ``profile``, just calibrated here, where :func:`find_kept` finds it; returns the path."""
    path = kept_path(this_machine(provider), quick)
    path.parent.mkdir(parents=True, exist_ok=True)
    how = "a quick calibration (a third of the sweep)" if quick else "a full calibration"
    return write_atomically(path, f"# Made by `explorer curve` on this machine, {how}; the next `explorer "
                            "curve` here reuses it (--recalibrate measures again).\n" + profile.to_yaml())
