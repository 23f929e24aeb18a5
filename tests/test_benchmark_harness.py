"""The benchmark harness (benchmarks/harness.py): interleaving, statistics, the JSON record and its
atomic write, the parameter grid and the suites' command line; and every benchmark of every suite and
every experiment answers --help."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from benchmarks import harness

ROOT = Path(__file__).resolve().parents[1]
#: every module of cases: the benchmark suites and the experiments
SUITES = ("benchmarks.runtime", "benchmarks.training", "benchmarks.search", "benchmarks.commands", "benchmarks.gpu",
          "experiments.fidelity", "experiments.search_value", "experiments.held_out", "experiments.resolution",
          "experiments.scan_model")

RECORD_KEYS = {"schema", "benchmark", "title", "description", "command", "commit", "dirty", "date", "machine",
               "figures", "notes"}
MACHINE_KEYS = {"cpu_model", "cpu_flags", "cores", "peak_gmacs_fp32", "platform", "python", "torch", "onnxruntime",
                "gpu"}
FIGURE_KEYS = {"name", "label", "unit", "reps", "median", "min", "max", "better"}


def test_rotated_order_gives_every_variant_every_position():
    names = ["a", "b", "c"]
    orders = [harness.rotated(names, r) for r in range(2 * len(names))]
    assert orders[0] == ["a", "b", "c"] and orders[1] == ["b", "c", "a"] and orders[2] == ["c", "a", "b"]
    assert len({tuple(o) for o in orders}) > 1
    for name in names:   # every position equally often over two full turns
        assert sorted(o.index(name) for o in orders) == [0, 0, 1, 1, 2, 2]
    for o in orders:
        assert sorted(o) == names


def test_interleave_calls_each_once_in_rotating_order_and_returns_by_name():
    calls: list[str] = []

    def fn(name):
        return lambda: calls.append(name) or name.upper()
    fns = {n: fn(n) for n in ("x", "y")}
    firsts = []
    for r in range(4):
        calls.clear()
        got = harness.interleave(fns, r)
        assert got == {"x": "X", "y": "Y"} and list(got) == ["x", "y"]
        assert sorted(calls) == ["x", "y"]
        firsts.append(calls[0])
    assert firsts.count("x") == 2 and firsts.count("y") == 2


def test_time_interleaved_rotates_blocks_and_times_every_call(monkeypatch):
    calls: list[str] = []
    fns = {n: (lambda n=n: calls.append(n)) for n in ("p", "q", "r")}
    ms = harness.time_interleaved(fns, rep=0, blocks=3, per_block=2)
    assert set(ms) == {"p", "q", "r"} and all(v >= 0 for v in ms.values())
    assert len(calls) == 3 * 3 * (1 + 2)
    block_starts = [calls[i] for i in range(0, len(calls), 3 * 3)]
    assert block_starts == ["p", "q", "r"]


def test_summary_median_min_max():
    assert harness.summary([3.0, 1.0, 2.0]) == (2.0, 1.0, 3.0)
    assert harness.summary([4.0, 1.0, 2.0, 10.0]) == (3.0, 1.0, 10.0)
    assert harness.summary([5]) == (5.0, 5.0, 5.0)
    with pytest.raises(ValueError):
        harness.summary([])


def test_machine_identity_has_the_keys():
    m = harness.machine()
    assert set(m) == MACHINE_KEYS
    assert isinstance(m["cpu_model"], str) and m["cpu_model"]
    assert isinstance(m["cpu_flags"], list) and set(m["cpu_flags"]) <= set(harness.RELEVANT_FLAGS)
    assert isinstance(m["cores"], int) and m["cores"] >= 1
    assert m["peak_gmacs_fp32"] is None or m["peak_gmacs_fp32"] > 0
    assert all(isinstance(m[k], str) for k in ("platform", "python", "torch", "onnxruntime"))
    assert m["gpu"] is None or isinstance(m["gpu"], str)


def test_a_copy_without_git_names_its_commit(tmp_path, monkeypatch):
    monkeypatch.delenv("BENCH_COMMIT", raising=False)
    assert harness.git_state(tmp_path) == ("unknown", True)
    monkeypatch.setenv("BENCH_COMMIT", "abc1234")
    assert harness.git_state(tmp_path) == ("abc1234", False)


def _bench(tmp_path, argv=("--reps", "3")) -> harness.Bench:
    bench = harness.Bench("/x/benchmarks/bench_toy.py", "a toy", "What it measures.\n\nUsage lines.")
    bench.parse_args(bench.parser(), ["--results", str(tmp_path), *argv])
    return bench


def test_record_is_written_with_every_schema_key(tmp_path, capsys):
    bench = _bench(tmp_path)
    bench.figure("t_ms", "toy time", "ms", better="lower")
    bench.figure("tau", "toy tau", "", better=None)
    for rep in bench.repetitions():
        bench.add("t_ms", [3.0, 1.0, 2.0][rep])
        bench.add("tau", 0.5)
    bench.note("a note")
    path = bench.finish(["benchmarks/runtime.py", "--only", "toy", "--reps", "3"])
    out = capsys.readouterr().out
    assert "rep 1/3" in out and "rep 3/3" in out and "toy time: 2 ms (1 to 3" in out
    assert path.parent == tmp_path / "bench_toy"
    rec = json.loads(path.read_text())
    assert set(rec) == RECORD_KEYS and set(rec["machine"]) == MACHINE_KEYS
    assert rec["schema"] == 1 and rec["benchmark"] == "bench_toy" and rec["title"] == "a toy"
    assert rec["description"] == "What it measures."
    assert rec["command"] == "python -m benchmarks.runtime --only toy --reps 3"
    assert isinstance(rec["dirty"], bool) and rec["notes"] == "a note"
    stamp = path.name.split("-")[0]
    assert path.name == f"{stamp}-{rec['commit']}.json" and len(stamp) == 16 and stamp.endswith("Z")
    assert rec["date"] == f"{stamp[:4]}-{stamp[4:6]}-{stamp[6:8]}T{stamp[9:11]}:{stamp[11:13]}:{stamp[13:15]}Z"
    t = rec["figures"][0]
    assert set(t) == FIGURE_KEYS
    assert t == {"name": "t_ms", "label": "toy time", "unit": "ms", "reps": [3.0, 1.0, 2.0], "median": 2.0,
                 "min": 1.0, "max": 3.0, "better": "lower"}
    assert rec["figures"][1]["better"] is None and rec["figures"][1]["reps"] == [0.5] * 3


def test_atomic_write_leaves_no_temp_file_and_replaces_whole(tmp_path, monkeypatch):
    bench = _bench(tmp_path)
    bench.figure("v", "value", "x")
    bench.add("v", 1.0)
    rec = bench.record(["benchmarks/bench_toy.py"])
    old_umask = os.umask(0o022)
    try:
        path = harness.write_record(rec, tmp_path)
    finally:
        os.umask(old_umask)
    assert [p.name for p in path.parent.iterdir()] == [path.name]
    assert json.loads(path.read_text()) == rec
    assert path.stat().st_mode & 0o044, "a record must be readable by others"

    def broken(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(harness.os, "replace", broken)
    with pytest.raises(OSError):
        harness.write_record({**rec, "notes": "second"}, tmp_path)
    assert [p.name for p in path.parent.iterdir()] == [path.name]   # no temp file, the old record intact
    assert json.loads(path.read_text())["notes"] == ""


def test_no_record_writes_nothing_and_bad_values_are_refused(tmp_path):
    bench = _bench(tmp_path, ["--no-record"])
    bench.figure("v", "value", "x")
    with pytest.raises(KeyError):
        bench.add("undeclared", 1.0)
    with pytest.raises(ValueError):
        bench.add("v", float("nan"))
    with pytest.raises(ValueError):
        bench.figure("v", "another label", "x")
    bench.add("v", 2.0)
    assert bench.finish() is None
    assert not any(tmp_path.iterdir())


def test_default_reps_at_least_three_and_option_parsed(tmp_path):
    bench = harness.Bench("bench_toy.py", "t", None, reps=1)
    args = bench.parse_args(bench.parser(), [])
    assert args.reps == 3 and args.no_record is False and args.results == harness.RESULTS
    assert list(harness.Bench("b.py", "t", None).repetitions(2)) == [0, 1]


def test_the_grid_is_every_combination_and_names_each_figure():
    combos = harness.grid(size=["224x224", "192x640"], threads=[1, 2])
    assert combos == [{"size": "224x224", "threads": 1}, {"size": "224x224", "threads": 2},
                      {"size": "192x640", "threads": 1}, {"size": "192x640", "threads": 2}]
    assert harness.suffix(combos[1]) == "224x224_2"


def _suite(calls: list) -> tuple:
    def bench_one(argv=None):
        calls.append(("one", list(argv)))

    def bench_big(argv=None):
        calls.append(("big", list(argv)))
    return (harness.Case(bench_one), harness.Case(bench_big, cpu=False, skip="needs a GPU"))


def test_a_suite_runs_only_what_it_is_asked_and_says_what_it_skips(capsys):
    calls: list = []
    harness.run_suite(_suite(calls), ["--only", "one", "--reps", "5"], module="toy")
    assert calls == [("one", ["--reps", "5"])]          # the other options go to the benchmark
    calls.clear()
    harness.run_suite(_suite(calls), ["--cpu", "--only", "bench_big", "--only", "one"], module="toy")
    assert calls == [("one", [])] and "skipped bench_big: needs a GPU" in capsys.readouterr().out
    harness.run_suite(_suite(calls), ["--list"], module="toy")
    assert "bench_big  (make benchmarks skips it: needs a GPU)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        harness.run_suite(_suite(calls), ["--only", "nothing"], module="toy")


def test_a_case_run_only_when_named_is_left_out_of_the_suites_plain_run_and_help(capsys):
    calls: list = []

    def bench_main(argv=None):
        calls.append(("main", list(argv)))

    def bench_variant(argv=None):
        calls.append(("variant", list(argv)))
    suite = (harness.Case(bench_main), harness.Case(bench_variant, named_only=True))
    harness.run_suite(suite, ["--reps", "3"], module="toy")
    assert calls == [("main", ["--reps", "3"])]          # one case left: it runs here, alone
    calls.clear()
    harness.run_suite(suite, ["--only", "variant", "--reps", "3"], module="toy")
    assert calls == [("variant", ["--reps", "3"])]
    calls.clear()
    harness.run_suite(suite, ["--help"], module="toy")   # the plain command's help is the main case's
    assert calls == [("main", ["--help"])]
    harness.run_suite(suite, ["--list"], module="toy")
    assert "bench_variant  (runs only with --only)" in capsys.readouterr().out


# Runs each case of each module given as an argument with --help, in one process: the heavy imports
# (torch, onnxruntime) are paid once per process instead of once per benchmark.
_HELP_RUNNER = """
import contextlib, importlib, io, json, sys
for module in sys.argv[1:]:
    for case in importlib.import_module(module).CASES:
        out = io.StringIO()
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
                case.run(["--help"])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException as exc:
            code, _ = 1, out.write(repr(exc))
        print(json.dumps({"script": f"{module} {case.name}", "code": code, "output": out.getvalue()}), flush=True)
"""


def _help_of(modules: list[str]) -> list[dict]:
    proc = subprocess.run([sys.executable, "-c", _HELP_RUNNER, *modules], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    rows = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert rows and proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return rows


def test_every_benchmark_answers_help():
    modules = [m for m in SUITES if "." in m]
    with ThreadPoolExecutor(max_workers=2) as pool:   # two processes, half the modules each
        rows = [r for part in pool.map(_help_of, [modules[0::2], modules[1::2]]) for r in part]
    assert len(rows) >= 20
    failed = [(r["script"], r["code"], r["output"][-500:]) for r in rows if r["code"] != 0]
    assert not failed, failed
    for r in rows:
        assert "--reps" in r["output"] and "--no-record" in r["output"] and "--results" in r["output"], r["script"]


def test_a_benchmark_answers_help_from_the_command_line():
    proc = subprocess.run([sys.executable, "-m", "benchmarks.runtime", "--only", "path0", "--help"],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "--reps" in proc.stdout and "Path 0" in proc.stdout
