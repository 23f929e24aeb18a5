"""The documentation site: it builds with `mkdocs build --strict`, and its two generated pages (the
CLI reference, the benchmark records) say what the parser and the records say."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOOK = ROOT / "docs" / "hooks" / "generate.py"


def _hook():
    """docs/hooks/generate.py as a module (it is not part of the package)."""
    spec = importlib.util.spec_from_file_location("docs_hook_generate", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_site_builds_strict(tmp_path):
    for name in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python"):
        pytest.importorskip(name)
    site = tmp_path / "site"
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})   # no banner in the output
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    cli = (site / "cli" / "index.html").read_text()
    assert "explorer search" in cli and "--budget" in cli
    assert (site / "benchmarks" / "index.html").is_file()
    assert (site / "reference" / "space" / "index.html").is_file()
    # every cross-reference rendered: no Sphinx role left as text on any page
    import re
    left = {str(p.relative_to(site)): m for p in site.rglob("*.html")
            if (m := re.findall(r":(?:func|class|meth|mod|attr|data|exc|obj):[`<]", p.read_text()))}
    assert not left, left


def _record(benchmark: str, stamp: str, commit: str, median: float) -> dict:
    return {
        "schema": 1, "benchmark": benchmark, "title": f"{benchmark} title", "description": "what it measures",
        "command": f"python benchmarks/{benchmark}.py --reps 3", "commit": commit, "dirty": False,
        "date": f"{stamp[:4]}-{stamp[4:6]}-{stamp[6:8]}T{stamp[9:11]}:{stamp[11:13]}:{stamp[13:15]}Z",
        "machine": {"cpu_model": "Test CPU 9000", "cpu_flags": ["avx2", "fma"], "cores": 4, "peak_gmacs_fp32": 78.4,
                    "platform": "Linux-x86_64", "python": "3.11.7", "torch": "2.13.0", "onnxruntime": "1.32.0"},
        "figures": [{"name": "whole_graph_ms", "label": "whole graph latency", "unit": "ms",
                     "reps": [median, median + 1.0, median - 1.0], "median": median, "min": median - 1.0,
                     "max": median + 1.0, "better": "lower"}],
        "notes": "",
    }


def _write(results: Path, rec: dict, stamp: str) -> Path:
    folder = results / rec["benchmark"]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stamp}-{rec['commit']}.json"
    path.write_text(json.dumps(rec))
    return path


def test_benchmark_page_shows_the_latest_record_of_each_benchmark(tmp_path):
    gen = _hook()
    results = tmp_path / "benchmarks" / "results"
    _write(results, _record("bench_runtime", "20261125T060000Z", "aaa1111", 11.25), "20261125T060000Z")
    newest = _write(results, _record("bench_runtime", "20261126T060000Z", "bbb2222", 9.75), "20261126T060000Z")
    _write(results, _record("bench_fit", "20261120T010203Z", "ccc3333", 1.5), "20261120T010203Z")
    found, problems = gen.latest_records(results)
    assert problems == []
    assert sorted(found) == ["bench_fit", "bench_runtime"]
    assert found["bench_runtime"][0] == newest
    page = gen.benchmarks_markdown(found, tmp_path)
    assert "9.75" in page and "11.25" not in page           # the latest record wins
    assert "bbb2222" in page and "aaa1111" not in page
    assert page.index("bench_fit title") < page.index("bench_runtime title")   # sorted by name
    assert "Test CPU 9000, 4 cores, peak 78.4 GMAC/s fp32" in page
    assert "benchmarks/results/bench_runtime/20261126T060000Z-bbb2222.json" in page


def test_benchmark_page_without_records_says_how_to_make_them(tmp_path):
    gen = _hook()
    found, problems = gen.latest_records(tmp_path / "missing")
    page = gen.benchmarks_markdown(found, tmp_path, problems)
    assert "No benchmark records yet" in page and "benchmarks/results/" in page


def test_a_broken_newest_record_gives_way_to_the_one_before(tmp_path):
    gen = _hook()
    results = tmp_path / "benchmarks" / "results"
    older = _write(results, _record("bench_runtime", "20261125T060000Z", "aaa1111", 11.25), "20261125T060000Z")
    broken = _record("bench_runtime", "20261126T060000Z", "bbb2222", 9.75)
    del broken["figures"][0]["median"]
    _write(results, broken, "20261126T060000Z")
    found, problems = gen.latest_records(results)
    assert found["bench_runtime"][0] == older
    assert len(problems) == 1 and "bbb2222" in problems[0]


def test_cli_page_has_every_command():
    gen = _hook()
    from explorer.cli import build_parser
    parser = build_parser()
    page = gen.cli_markdown(parser)
    commands = gen.subcommands(parser)
    assert len(commands) > 10
    for name, _, sub in commands:
        assert f"\n## explorer {name}\n" in page, name
        for child, _, _ in gen.subcommands(sub):
            assert f"\n### explorer {name} {child}\n" in page, f"{name} {child}"
    assert "usage: explorer search" in page


def test_figure_references_take_the_latest_records_value(tmp_path):
    gen = _hook()
    results = tmp_path / "benchmarks" / "results"
    _write(results, _record("bench_runtime", "20261125T060000Z", "aaa1111", 11.25), "20261125T060000Z")
    _write(results, _record("bench_runtime", "20261126T060000Z", "bbb2222", 9.75), "20261126T060000Z")
    found, _ = gen.latest_records(results)
    assert gen.figure_text(found, "bench_runtime", "whole_graph_ms") == "9.75 ms (8.75 to 10.75, 3 reps)"
    assert gen.figure_text(found, "bench_runtime", "no_such_figure") is None
    assert gen.figure_text(found, "bench_nothing", "whole_graph_ms") is None
