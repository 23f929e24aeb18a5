"""The one harness every benchmark and experiment uses: suites, repetitions, interleaving, printing
and the JSON record.

A suite is a module of benchmarks (``benchmarks/runtime.py``, ...), each a function that parses its own
options, declares what it measures, runs its repetitions and hands the harness one value per figure
per repetition::

    def bench_path0(argv=None):
        '''What it measures: the docstring's first paragraph is the record's description.'''
        bench = Bench("bench_path0", "one-line title", bench_path0.__doc__)   # the record's name
        ap = bench.parser()                                   # --reps, --no-record, --results already there
        args = bench.parse_args(ap, argv)
        bench.figure("whole_ms", "whole graph latency", "ms", better="lower")
        for rep in bench.repetitions():                       # prints each repetition's figures after it
            ms = time_interleaved({"whole": run_whole, "staged": run_staged}, rep)
            bench.add("whole_ms", ms["whole"])
        bench.finish()                                        # medians (min-max), then the record

    CASES = (Case(bench_path0), Case(bench_gpu, cpu=False, skip="needs a GPU"))
    if __name__ == "__main__":
        run_suite(CASES)                                      # --list, --only NAME, --cpu

A benchmark whose figures vary along a parameter (an image size, a thread count) takes its values from
a grid (``grid``, the asv ``params`` shape) and names each figure with the combination's ``suffix``.

Variants being compared run inside every repetition, in an order that rotates from round to round
(``rotated``): a machine whose speed drifts, or whose caches hold what ran last, then touches every
variant alike instead of charging one variant with a slow spell or with its predecessor's leftovers.

The record goes to ``benchmarks/results/<record name>/<UTC YYYYmmddTHHMMSSZ>-<short commit>.json``
(schema 1, see ``record``), written atomically; the docs' benchmark page is generated from the latest
record of each benchmark.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import math
import os
import platform
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence, TypeVar

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SCHEMA = 1
DEFAULT_REPS = 3
#: the CPU flags that decide which kernels onnxruntime and PyTorch run (vector width, FMA, int8 dot products)
RELEVANT_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512_vnni", "avx512_bf16",
                  "avx_vnni", "amx_tile", "amx_int8", "amx_bf16", "neon", "asimd", "asimddp", "sve", "i8mm")

T = TypeVar("T")


# -- interleaving ---------------------------------------------------------------------------------
def rotated(names: Sequence[T], round_: int) -> list[T]:
    """The order of round ``round_``: ``names`` rotated by ``round_`` places, and reversed every other
    full turn, so that each variant takes every position and follows every other variant equally often
    over ``2 * len(names)`` rounds (what ran just before a call can slow or speed it)."""
    n = len(names)
    if n == 0:
        return []
    base = list(names) if (round_ // n) % 2 == 0 else list(reversed(names))
    k = round_ % n
    return base[k:] + base[:k]


def interleave(fns: dict[str, Callable[[], T]], round_: int) -> dict[str, T]:
    """Calls every one of ``fns`` once, in round ``round_``'s rotated order; their results by name
    (in the order of ``fns``)."""
    got = {name: fns[name]() for name in rotated(list(fns), round_)}
    return {name: got[name] for name in fns}


def time_interleaved(fns: dict[str, Callable[[], object]], rep: int = 0, blocks: int = 10,
                     per_block: int = 4) -> dict[str, float]:
    """The median wall time in ms of each of ``fns`` over ``blocks`` rounds; in each round every
    function runs once untimed (its buffers back in the caches after the others') and ``per_block``
    times timed, in that round's rotated order (``rep`` continues the rotation across repetitions)."""
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for b in range(blocks):
        for name in rotated(list(fns), rep * blocks + b):
            fn = fns[name]
            fn()
            for _ in range(per_block):
                t0 = time.perf_counter()
                fn()
                samples[name].append((time.perf_counter() - t0) * 1000.0)
    return {name: statistics.median(s) for name, s in samples.items()}


def summary(values: Sequence[float]) -> tuple[float, float, float]:
    """(median, min, max) of one figure's repetitions."""
    if not values:
        raise ValueError("no values")
    return float(statistics.median(values)), float(min(values)), float(max(values))


def grid(**axes: Sequence) -> list[dict]:
    """Every combination of the axes' values, the first axis slowest (asv's ``params``):
    ``grid(size=["224x224", "192x640"], threads=[1, 2])`` gives four dicts."""
    names = list(axes)
    return [dict(zip(names, values)) for values in itertools.product(*(axes[n] for n in names))]


def suffix(params: Mapping) -> str:
    """The suffix of a figure measured at ``params``: its values joined by ``_`` (``224x224_2``)."""
    return "_".join(str(v) for v in params.values())


# -- the machine and the code ---------------------------------------------------------------------
def _cpuinfo() -> str:
    try:
        return Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def _version(module: str) -> str:
    try:
        return __import__(module).__version__
    except Exception:   # not installed, or broken: the record says so rather than failing the run
        return "unavailable"


def _peak_gmacs_fp32() -> float | None:
    """The nominal fp32 peak from ``explorer.calibration.peak.host_peak`` (flags, cores, clock: no
    measuring), or None where it cannot be had."""
    try:
        from explorer.calibration.peak import host_peak
        return round(float(host_peak().fp32_gmacs), 1)
    except Exception:
        return None


def machine() -> dict:
    """The identity of this machine, as the record's ``machine`` holds it."""
    info = _cpuinfo()
    model = re.search(r"^(?:model name|Hardware|Processor)\s*:\s*(.+)$", info, re.M)
    flags = re.search(r"^(?:flags|Features)\s*:(.*)$", info, re.M)
    have = set(flags.group(1).split()) if flags else set()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return {"cpu_model": model.group(1).strip() if model else (platform.processor() or platform.machine()),
            "cpu_flags": [f for f in RELEVANT_FLAGS if f in have],
            "cores": cores,
            "peak_gmacs_fp32": _peak_gmacs_fp32(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": _version("torch"),
            "onnxruntime": _version("onnxruntime"),
            "gpu": _gpu_name()}


def _gpu_name() -> str | None:
    """The name of the GPU PyTorch trains on, where the benchmark imported torch and it sees one."""
    torch = sys.modules.get("torch")
    try:
        return torch.cuda.get_device_name() if torch is not None and torch.cuda.is_available() else None
    except Exception:   # a broken driver: the record says nothing rather than failing the run
        return None


def git_state(root: Path = ROOT) -> tuple[str, bool]:
    """(short commit, dirty) of the checkout; ("unknown", True) outside git. The results and label
    folders are left out of the dirty check: records and cached trainings written there are not a
    change to what was measured. A copy of a clean checkout without its ``.git`` (a benchmark run on
    another machine) names its commit in ``BENCH_COMMIT``."""
    if os.environ.get("BENCH_COMMIT"):
        return os.environ["BENCH_COMMIT"], False
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout
    try:
        commit = git("rev-parse", "--short", "HEAD").strip()
        changes = git("status", "--porcelain", "--", ".", ":(exclude)benchmarks/results",
                      ":(exclude)benchmarks/labels")
    except (OSError, subprocess.CalledProcessError):
        return "unknown", True
    return commit or "unknown", bool(changes.strip())


def image_size(text: str) -> tuple[int, int]:
    """An HxW option (``224x224``) as (height, width): the argparse ``type`` of every size option."""
    h, w = (int(x) for x in text.lower().split("x"))
    return h, w


def python_path() -> str:
    """PYTHONPATH for a child process of a benchmark: the repository first, then what this one had
    (packages installed beside the project on another machine, say)."""
    return os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH", "")]))


def command_line(argv: Sequence[str] | None = None) -> str:
    """The command as a user types it from the repository root: ``python -m benchmarks.runtime --only
    path0 --reps 5``."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]).resolve() if argv else Path("?")
    try:
        module = script.relative_to(ROOT).with_suffix("").as_posix().replace("/", ".")
    except ValueError:
        return shlex.join(["python", str(script), *argv[1:]])
    return shlex.join(["python", "-m", module, *argv[1:]])


def write_record(record: dict, results: Path = RESULTS) -> Path:
    """Writes ``record`` to ``results/<benchmark>/<stamp>-<commit>.json`` through a temporary file in the
    same folder and ``os.replace``: a reader (the docs' generator) sees the whole record or none."""
    stamp = datetime.datetime.strptime(record["date"], "%Y-%m-%dT%H:%M:%SZ").strftime("%Y%m%dT%H%M%SZ")
    folder = Path(results) / record["benchmark"]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stamp}-{record['commit']}.json"
    text = json.dumps(record, indent=1, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.fchmod(fd, 0o666 & ~umask)   # mkstemp makes it private; a record is for everyone to read
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# -- the benchmark --------------------------------------------------------------------------------
@dataclass
class Figure:
    name: str
    label: str
    unit: str
    better: str | None
    reps: list[float] = field(default_factory=list)

    def to_dict(self) -> dict:
        median, lo, hi = summary(self.reps)
        return {"name": self.name, "label": self.label, "unit": self.unit, "reps": list(self.reps),
                "median": median, "min": lo, "max": hi, "better": self.better}


def _fmt(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 1e4 else f"{value:.4g}"


def description_of(doc: str | None) -> str:
    """A docstring's first paragraph on one line: the record's description."""
    first = (doc or "").strip().split("\n\n")[0]
    return " ".join(first.split())


class Bench:
    """One benchmark run: its declared figures, their values per repetition, and its record."""

    def __init__(self, name: str, title: str, doc: str | None, reps: int = DEFAULT_REPS) -> None:
        self.name = Path(name).stem       # the record's name (a script's path gives its stem)
        self.title = title
        self.description = description_of(doc)
        self.doc = doc or ""
        self.default_reps = max(reps, DEFAULT_REPS)
        self.figures: dict[str, Figure] = {}
        self.notes: list[str] = []
        self.args: argparse.Namespace | None = None
        self.started = datetime.datetime.now(datetime.timezone.utc)
        self._rep_values: list[tuple[str, float]] = []

    def parser(self, **kwargs) -> argparse.ArgumentParser:
        """An ArgumentParser with the harness's options: --reps, --no-record, --results."""
        ap = argparse.ArgumentParser(prog=self.name, description=self.title, epilog=self.doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)
        ap.add_argument("--reps", type=int, default=self.default_reps,
                        help=f"interleaved repetitions (default {self.default_reps})")
        ap.add_argument("--no-record", action="store_true", help="print only; write no JSON record")
        ap.add_argument("--results", type=Path, default=RESULTS,
                        help="folder of the records (default benchmarks/results)")
        return ap

    def parse_args(self, ap: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> argparse.Namespace:
        self.args = ap.parse_args(argv)
        if self.args.reps < 1:
            ap.error("--reps must be at least 1")
        return self.args

    @property
    def reps(self) -> int:
        return self.args.reps if self.args is not None else self.default_reps

    def figure(self, name: str, label: str, unit: str, better: str | None = None) -> str:
        """Declares a figure (once; again with the same description is fine); returns its name."""
        if better not in ("lower", "higher", None):
            raise ValueError(f"better={better!r}: lower, higher or None")
        new = Figure(name, label, unit, better)
        old = self.figures.setdefault(name, new)
        if (old.label, old.unit, old.better) != (label, unit, better):
            raise ValueError(f"figure {name!r} declared twice, differently")
        return name

    def add(self, name: str, value: float) -> float:
        """One value of the declared figure ``name`` (the current repetition's, or a one-off's)."""
        if name not in self.figures:
            raise KeyError(f"figure {name!r} not declared (Bench.figure)")
        value = float(value)
        if not math.isfinite(value):   # JSON holds no NaN: fail here, where the cause is, not at the end
            raise ValueError(f"figure {name!r}: {value} is not a finite number")
        self.figures[name].reps.append(value)
        self._rep_values.append((name, value))
        return value

    def note(self, text: str) -> None:
        """A sentence for the record's notes (and the output)."""
        self.notes.append(text)
        print(f"note: {text}", flush=True)

    def repetitions(self, reps: int | None = None) -> Iterator[int]:
        """0 .. reps-1 (``--reps`` by default); after each, the values added during it are printed."""
        n = self.reps if reps is None else reps
        for rep in range(n):
            self._rep_values = []
            t0 = time.perf_counter()
            yield rep
            values = [f"{self.figures[k].label} {_fmt(v)} {self.figures[k].unit}".rstrip() for k, v in self._rep_values]
            # a long list reads better one figure a line
            sep = ", " if len(values) <= 4 else "\n  "
            print(f"rep {rep + 1}/{n} ({time.perf_counter() - t0:.0f} s):" + (" " if len(values) <= 4 else "\n  ")
                  + sep.join(values), flush=True)

    def record(self, argv: Sequence[str] | None = None) -> dict:
        """The record (schema 1) of the figures so far; figures without values are left out."""
        commit, dirty = git_state()
        return {"schema": SCHEMA, "benchmark": self.name, "title": self.title, "description": self.description,
                "command": command_line(argv), "commit": commit, "dirty": dirty,
                "date": self.started.strftime("%Y-%m-%dT%H:%M:%SZ"), "machine": machine(),
                "figures": [f.to_dict() for f in self.figures.values() if f.reps],
                "notes": " ".join(self.notes)}

    def finish(self, argv: Sequence[str] | None = None) -> Path | None:
        """Prints each figure's median (min-max) over its repetitions and, unless --no-record, writes the
        record; returns its path."""
        print(f"\n{self.title}: medians over the repetitions (min-max)")
        for f in self.figures.values():
            if f.reps:
                median, lo, hi = summary(f.reps)
                print(f"  {f.label}: {_fmt(median)}{' ' + f.unit if f.unit else ''} ({_fmt(lo)} to {_fmt(hi)}; "
                      f"{len(f.reps)} rep{'' if len(f.reps) == 1 else 's'}"
                      + (f", {f.better} is better" if f.better else "") + ")")
        if self.args is not None and self.args.no_record:
            return None
        path = write_record(self.record(argv), self.args.results if self.args is not None else RESULTS)
        print(f"record: {path}", flush=True)
        return path


# -- the suite ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    """One benchmark of a suite: its function (named after its record), whether ``make benchmarks``
    runs it (``cpu``: it fits a CPU in minutes) or what keeps it out (``skip``), and whether it runs only
    when ``--only`` names it (``named_only``: a variant of the suite's experiment, hours long, that the
    suite's plain command must not start as well)."""

    run: Callable[[Sequence[str] | None], object]
    cpu: bool = True
    skip: str = ""
    named_only: bool = False

    @property
    def name(self) -> str:
        return self.run.__name__


def _selected(cases: Sequence[Case], only: Sequence[str], cpu: bool, ap: argparse.ArgumentParser) -> list[Case]:
    by_name = {c.name: c for c in cases}
    for name in only:
        if name not in by_name and f"bench_{name}" not in by_name:
            ap.error(f"no benchmark {name!r} in this suite: {', '.join(by_name)}")
    chosen = ([c for c in cases if c.name in only or c.name.removeprefix("bench_") in only] if only
              else [c for c in cases if not c.named_only])
    if cpu:
        for c in chosen:
            if not c.cpu:
                print(f"skipped {c.name}: {c.skip}", flush=True)
        chosen = [c for c in chosen if c.cpu]
    return chosen


def run_suite(cases: Sequence[Case], argv: Sequence[str] | None = None, module: str | None = None) -> None:
    """A suite's command line: ``--list`` its benchmarks, ``--only NAME`` (repeatable; default all but
    those run only when named) runs some, ``--cpu`` leaves out those that do not fit a CPU (saying why);
    every other option goes to the benchmarks run. One benchmark runs in this process; several run one
    after another, each in a process of its own (its threads, pools and imports its own)."""
    ap = argparse.ArgumentParser(prog=f"python -m {module or _caller_module()}", add_help=False,
                                 description="Runs benchmarks of this suite; NAME --help: its options.")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and what make benchmarks skips")
    ap.add_argument("--only", action="append", default=[], metavar="NAME", help="run NAME (repeatable)")
    ap.add_argument("--cpu", action="store_true", help="leave out what does not fit a CPU in minutes")
    args, rest = ap.parse_known_args(argv)
    by_default = [c for c in cases if not c.named_only]
    if args.list or (not args.only and len(by_default) > 1 and rest in (["-h"], ["--help"])):
        ap.print_help()
        for c in cases:
            print(f"  {c.name}{'' if c.cpu else f'  (make benchmarks skips it: {c.skip})'}"
                  f"{'  (runs only with --only)' if c.named_only else ''}")
        return
    chosen = _selected(cases, args.only, args.cpu, ap)
    if len(chosen) == 1:
        chosen[0].run(rest)
        return
    for c in chosen:
        cmd = [sys.executable, "-m", module or _caller_module(), "--only", c.name, *rest]
        print(f"\n== {c.name}: {shlex.join(cmd[1:])}", flush=True)
        if subprocess.run(cmd, cwd=ROOT).returncode != 0:
            raise SystemExit(f"{c.name} failed")


def _caller_module() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return spec.name if spec is not None and spec.name else Path(sys.argv[0]).stem
