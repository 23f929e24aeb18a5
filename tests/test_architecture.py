"""The package's shape: layers (import-linter contracts in pyproject.toml), no import cycles, no
private names imported across packages, a probe that needs nothing but numpy and onnxruntime,
modules and functions small enough to read, and code that ruff's checks pass."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "explorer"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
LINTED = ("explorer", "benchmarks", "experiments", "tests")   # what ruff checks ([tool.ruff] in pyproject.toml)


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(name: str, path: Path) -> list[tuple[str, list[str], int]]:
    """(imported module, names taken from it, line) for every import in the module, anywhere."""
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.append((base, [a.name for a in node.names], node.lineno))
    return found


def test_layer_contracts_hold():
    pytest.importorskip("importlinter")
    run = subprocess.run([str(Path(sys.executable).with_name("lint-imports")), "--no-cache"], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def _ruff() -> str | None:
    """This environment's ruff (the wheel puts it beside the interpreter), else one on PATH."""
    beside = Path(sys.executable).with_name("ruff")
    if beside.exists():
        return str(beside)
    try:
        from ruff.__main__ import find_ruff_bin
        return str(find_ruff_bin())
    except (ImportError, FileNotFoundError):
        return shutil.which("ruff")


def test_ruff_finds_nothing():
    """ruff's checks ([tool.ruff.lint] in pyproject.toml: unused imports and variables, undefined names,
    statements, syntax) pass on the package, the benchmarks, the experiments and the tests."""
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed (the test extra has it: pip install -e '.[test]')")
    run = subprocess.run([ruff, "check", "--no-cache", "--output-format", "concise", *LINTED], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def test_no_import_cycles():
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        for target, names, _ in _imports(name, path):
            for candidate in [f"{target}.{n}" for n in names] + [target]:
                if candidate in modules and candidate != name:
                    graph[name].add(candidate)
                    break
    # Tarjan's strongly connected components: a component of more than one module is a cycle
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def _package_of(module: str, modules: dict[str, Path]) -> str:
    return module if modules.get(module, Path()).name == "__init__.py" else module.rpartition(".")[0]


def _private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def test_no_private_names_imported_across_packages():
    modules = _modules()
    bad = []
    for name, path in modules.items():
        here = _package_of(name, modules)
        for target, names, line in _imports(name, path):
            if not target.startswith("explorer"):
                continue
            for n in names or [""]:
                module = f"{target}.{n}" if f"{target}.{n}" in modules else target
                if _package_of(module, modules) == here:
                    continue
                if _private(n) or any(_private(part) for part in module.split(".")):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {target}.{n}")
    assert not bad, "\n".join(bad)


def _run_on_import(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """The module's import statements outside any function: those its import runs (at the top, in a
    ``try``, an ``if`` or a class body alike)."""
    in_functions = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                    for n in ast.walk(f) if n is not f}
    return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in in_functions]


def test_probe_imports_only_the_standard_library_numpy_and_onnxruntime():
    """The probe runs on a device that has Python, numpy and onnxruntime and nothing else; onnx is
    allowed only inside functions (graph rewrites the probe itself never calls)."""
    allowed = set(sys.stdlib_module_names) | {"numpy", "onnxruntime"}
    modules = {n: p for n, p in _modules().items() if n == "explorer.probe" or n.startswith("explorer.probe.")}
    # a check that reads no module passes anything: these read the probe's package, its entry point and
    # the graph rewrites (which import onnx, inside their functions)
    assert {"explorer.probe", "explorer.probe.run", "explorer.probe.rewrites"} <= modules.keys(), sorted(modules)
    bad = []
    for name, path in modules.items():
        for target, _, line in _imports(name, path):
            top = target.split(".")[0]
            if target.startswith("explorer.probe") or top == "__future__":
                continue
            if top == "explorer":
                bad.append(f"{path.name}:{line} imports {target}")
            elif top not in allowed and not (top == "onnx"):
                bad.append(f"{path.name}:{line} imports {target}")
        for node in _run_on_import(ast.parse(path.read_text())):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
            if any(n.split(".")[0] == "onnx" for n in names):
                bad.append(f"{path.name}:{node.lineno} imports onnx at module level")
    assert not bad, "\n".join(bad)


def test_modules_and_functions_stay_small():
    long_modules, long_functions = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = path.read_text().splitlines()
        if len(lines) > MAX_MODULE_LINES:
            long_modules.append(f"{path.relative_to(ROOT)}: {len(lines)} lines")
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {length} lines")
    for path in sorted([*(ROOT / "tests").rglob("*.py"), *(ROOT / "benchmarks").rglob("*.py")]):
        lines = len(path.read_text().splitlines())
        if lines > MAX_MODULE_LINES:   # the tests and benchmarks are read as often as the package
            long_modules.append(f"{path.relative_to(ROOT)}: {lines} lines")
    assert not long_modules, "\n".join(long_modules)
    assert not long_functions, "\n".join(long_functions)


def test_the_command_line_and_the_runtime_load_without_torch():
    """`explorer run` deploys on devices without PyTorch, and `explorer --help` answers at once: neither
    the command line's modules nor the runtime import torch until a command needs it."""
    code = ("import sys; import explorer.cli, explorer.deploy.runtime, explorer.probe; "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0
