"""What the benchmarks and experiments promise about themselves: every benchmark or experiment the
package's comments name exists and has a record, every suite has records and every record a benchmark,
and the benchmarks stay a few small suites that put nothing on ``sys.path``."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
MODULES = ("benchmarks.runtime", "benchmarks.training", "benchmarks.search", "benchmarks.commands", "benchmarks.gpu",
           "experiments.fidelity", "experiments.search_value", "experiments.held_out", "experiments.resolution",
           "experiments.scan_model", "experiments.photometric", "experiments.early_paths",
           "experiments.table2", "experiments.low_res_pass")
NAMED = re.compile(r"\bbench_\w+")
PATH = re.compile(r"\b(?:benchmarks|experiments)/[\w/]+\.py\b")


def _cases() -> dict[str, str]:
    """{record name: module} of every benchmark and experiment."""
    return {case.name: module for module in MODULES for case in importlib.import_module(module).CASES}


def _has_record(name: str) -> bool:
    return any((RESULTS / name).glob("*.json"))


def _named_in_package() -> dict[str, list[str]]:
    named: dict[str, list[str]] = {}
    for path in sorted((ROOT / "explorer").rglob("*.py")):
        for name in NAMED.findall(path.read_text()):
            named.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return named


def test_every_benchmark_the_package_names_exists_and_has_a_record():
    cases = _cases()
    named = _named_in_package()
    assert named, "the package names no benchmark: is the pattern still right?"
    missing = {n: files for n, files in named.items() if n not in cases}
    assert not missing, f"named in the package, but no benchmark or experiment: {missing}"
    unrecorded = {n: files for n, files in named.items() if not _has_record(n)}
    assert not unrecorded, f"named in the package, but no record under benchmarks/results/: {unrecorded}"


def test_every_file_the_package_names_under_benchmarks_or_experiments_exists():
    named = {p for path in (ROOT / "explorer").rglob("*.py") for p in PATH.findall(path.read_text())}
    assert not [p for p in named if not (ROOT / p).is_file()]


@pytest.mark.parametrize("module", MODULES)
def test_every_suite_and_experiment_has_a_record(module):
    names = [case.name for case in importlib.import_module(module).CASES]
    assert any(_has_record(n) for n in names), f"{module}: no record of {names}"


#: records whose experiment is gone, each kept for a reason: the evidence of why what it measured is gone too
RETIRED = {"bench_cascade": "cascaded exits, removed: the record is the evidence why (docs/evidence.md)"}


def test_every_record_belongs_to_a_benchmark_or_an_experiment():
    cases = _cases()
    orphans = sorted(p.name for p in RESULTS.iterdir() if p.is_dir() and p.name not in cases and p.name not in RETIRED)
    assert not orphans, f"records of no benchmark: {orphans}"


@pytest.mark.parametrize("name", sorted(RETIRED))
def test_a_retired_record_is_kept_and_belongs_to_no_benchmark(name):
    assert name not in _cases(), f"{name} is a benchmark again: take it out of RETIRED"
    assert _has_record(name), f"{name} is retired but has no record under benchmarks/results/: {RETIRED[name]}"
    assert f"benchmarks.md#{name}" in (ROOT / "docs" / "evidence.md").read_text(), \
        f"{name}: the evidence page, the reason its record is kept, no longer links it"


def test_the_benchmarks_are_a_few_small_suites_that_leave_sys_path_alone():
    files = sorted((ROOT / "benchmarks").glob("*.py"))
    assert len(files) <= 10
    assert sum(len(f.read_text().splitlines()) for f in files) <= 3000
    for f in [*files, *(ROOT / "experiments").rglob("*.py")]:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", "") == "sys":
                pytest.fail(f"{f.relative_to(ROOT)} reads or edits sys.path")
