"""What every command group shares: the one-line-error parser and argument types."""

from __future__ import annotations

import argparse
import sys

from explorer.errors import UserError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + line)
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(2)


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not HxW (e.g. 224x224)") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"'{text}': sides must be positive")
    return h, w


def _count(text: str) -> float:
    """2.5M, 300k, 1500000."""
    t = text.strip().lower()
    mult = {"k": 1e3, "m": 1e6, "g": 1e9}.get(t[-1:], 1.0)
    try:
        return float(t[:-1] if t[-1:] in "kmg" else t) * mult
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a count (e.g. 2.5M)") from None


def _ms(text: str) -> float:
    from explorer.anytime import _parse_quantity
    try:
        return _parse_quantity(text, "time")
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _duration_s(text: str) -> float:
    t = text.strip().lower()
    units = {"s": 1, "m": 60, "h": 3600}
    try:
        return float(t[:-1]) * units[t[-1]] if t[-1:] in units else float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a duration (e.g. 10m, 90s, 1h)") from None


def _add_supervision(s: argparse.ArgumentParser) -> None:
    s.add_argument("--supervision", default="supervised", choices=["supervised", "self", "mixed"],
                   help="supervised: L1 on dense depth (default); self: photometric reprojection between "
                   "neighbouring frames plus the scan row for metric scale (needs sequence data: "
                   "synthetic-seq, kitti-seq:DRIVE, frames:FOLDER); mixed: both where labels exist")
    s.add_argument("--poses", default="net", choices=["net", "given"],
                   help="self-supervision's camera motion: a pose network trained jointly (default), or "
                   "the data's own poses (synthetic-seq, KITTI oxts, a folder's poses.txt)")
    s.add_argument("--depth-hints", action="store_true",
                   help="self-supervision with depth hints (needs --poses given): each training frame's "
                   "depth is first optimised on the photometric loss from the scan, then pulls every exit "
                   "where it explains the neighbouring frames better (computed once per data set, cached)")

