"""The runtime installs alone: ``anytime-explorer-runtime`` (runtime/pyproject.toml) is a wheel of the
package's runtime, manifest reader and command line whose dependencies are exactly what ``explorer
run`` imports, and that wheel, put into a fresh environment without torch, runs an exported network.
These are the steps of docs/guides/deploying.md's "On the device"."""

import json
import shutil
import subprocess
import sys
import venv
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]
SIZE = (64, 96)


def _requirements(dist: metadata.Distribution) -> list[Requirement]:
    reqs = [Requirement(r) for r in dist.requires or []]
    return [r for r in reqs if r.marker is None or r.marker.evaluate({"extra": ""})]


def _closure(names: list[str]) -> dict[str, metadata.Distribution]:
    """The installed distributions ``names`` need, theirs included, as this environment has them."""
    found: dict[str, metadata.Distribution] = {}
    todo = list(names)
    while todo:
        name = todo.pop().lower().replace("_", "-")
        if name in found:
            continue
        found[name] = dist = metadata.distribution(name)
        todo += [r.name for r in _requirements(dist)]
    return found


def _site_of(dists: dict[str, metadata.Distribution], into: Path) -> None:
    """A site folder holding only ``dists``: links to their top-level files in this environment."""
    into.mkdir()
    for dist in dists.values():
        for top in {Path(f.parts[0]) for f in dist.files or [] if not f.parts[0].startswith("..")}:
            source = Path(dist.locate_file(top))
            if source.exists() and not (into / top.name).exists() and top.name != "__pycache__":
                (into / top.name).symlink_to(source)


@pytest.fixture(scope="module")
def runtime_wheel(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("runtime-wheel")
    source = tmp / "source"   # built from a copy: setuptools writes build/ and the egg-info beside the sources
    shutil.copytree(ROOT / "explorer", source / "explorer", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "runtime", source / "runtime", ignore=shutil.ignore_patterns("build"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "./runtime", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp / "dist")], check=True, cwd=source, capture_output=True)
    return next((tmp / "dist").glob("anytime_explorer_runtime-*.whl"))


def _wheel_requirements(wheel: Path) -> list[Requirement]:
    import zipfile
    with zipfile.ZipFile(wheel) as zf:
        meta = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        lines = zf.read(meta).decode().splitlines()
    return [Requirement(line.split(":", 1)[1].strip()) for line in lines if line.startswith("Requires-Dist:")]


def test_the_runtime_wheel_holds_the_runtime_and_needs_no_torch(runtime_wheel):
    import zipfile
    names = zipfile.ZipFile(runtime_wheel).namelist()
    assert "explorer/deploy/runtime.py" in names and "explorer/deploy/manifest.py" in names
    assert "explorer/cli/deploy.py" in names and "explorer/deploy/curve.py" in names   # explorer curve --device
    assert not any(n.startswith(("explorer/study/", "explorer/training/", "explorer/model/")) for n in names)
    reqs = {r.name: str(r.specifier) for r in _wheel_requirements(runtime_wheel)}
    assert set(reqs) == {"numpy", "onnx", "onnxruntime", "pyyaml", "pydantic", "pillow", "rich"}
    # the same bounds as the full package's, and nothing torch needs comes with them
    tomllib = pytest.importorskip("tomllib")
    full = {Requirement(r).name: str(Requirement(r).specifier)
            for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]}
    assert {name: full[name] for name in reqs} == reqs
    assert "torch" not in _closure(list(reqs)) and "pandas" not in _closure(list(reqs))
    assert runtime_wheel.name.startswith(f"anytime_explorer_runtime-{_version()}-")


def _version() -> str:
    from explorer import __version__
    return __version__


@pytest.mark.slow
def test_a_fresh_environment_without_torch_runs_an_exported_network(runtime_wheel, tmp_path):
    import torch
    from PIL import Image

    from conftest import TINY_DATA
    from explorer.deploy.export import Measurement, export_network
    from explorer.model import build_network
    from explorer.space import paper_candidate

    torch.manual_seed(0)
    export_network(build_network(paper_candidate()), tmp_path / "winner", SIZE, devices=("tx2",))
    # measured on frames with depth, an export carries the validation frames explorer curve measures on
    export_network(build_network(paper_candidate()), tmp_path / "measured", SIZE, devices=("tx2",),
                   measurement=Measurement(TINY_DATA, 4))
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (*SIZE, 3), dtype=np.uint8)).save(tmp_path / "frame.png")
    np.savetxt(tmp_path / "scan.csv", rng.uniform(0.5, 8.0, (1, SIZE[1])), delimiter=",")

    env_dir = tmp_path / "device"
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # the wheel's dependencies, and only those, as this environment has them (the test runs offline)
    _site_of(_closure([r.name for r in _wheel_requirements(runtime_wheel)]), tmp_path / "deps")
    (site / "deps.pth").write_text(str(tmp_path / "deps") + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
                    str(runtime_wheel)], check=True, capture_output=True)

    def explorer(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(env_dir / "bin" / "explorer"), *args], cwd=tmp_path, capture_output=True,
                              text=True, env={"PATH": str(env_dir / "bin"), "HOME": str(tmp_path)})

    no_torch = subprocess.run([str(python), "-c", "import torch"], capture_output=True, text=True)
    assert no_torch.returncode != 0 and "No module named 'torch'" in no_torch.stderr
    done = explorer("run", "winner", "--image", "frame.png", "--scan", "scan.csv", "--deadline", "500ms",
                    "--out", "depth.png")
    assert done.returncode == 0, done.stderr
    assert "returned path 4" in done.stdout and "wrote depth.png" in done.stdout
    assert Image.open(tmp_path / "depth.png").size == (SIZE[1], SIZE[0])
    res = json.loads(explorer("run", "winner", "--image", "frame.png", "--scan", "scan.csv", "--deadline", "0.001ms",
                              "--json").stdout)
    assert res["path"] == 0   # path 0 is always there, however short the deadline

    # the anytime curve here, predicted with the costs the manifest holds for a device, and never torch
    curve = subprocess.run([str(python), "-c", "import sys; from explorer.cli import main; rc = main(sys.argv[1:]); "
                            "assert 'torch' not in sys.modules and 'pandas' not in sys.modules; sys.exit(rc)",
                            "curve", "measured", "--device", "tx2", "--frames", "4", "--deadlines", "3"],
                           cwd=tmp_path, capture_output=True, text=True, env={"HOME": str(tmp_path)})
    assert curve.returncode == 0, curve.stderr
    assert "predicted by tx2 (the export's expected costs)" in curve.stdout
    written = json.loads((tmp_path / "measured" / "anytime_curve.json").read_text())
    assert written["frames"] == 4 and len(written["measured"]["loss"]) == 3 and written["predicted_from"] == "manifest"
    unpriced = explorer("curve", "measured", "--frames", "4")
    assert unpriced.returncode == 2 and unpriced.stderr.count("\n") == 1, unpriced.stderr
    assert "this export prices tx2" in unpriced.stderr and "probe bundle" in unpriced.stderr
    assert "Traceback" not in unpriced.stderr

    # a command that needs the full package says so in one line
    search = explorer("search", "--space", "tiny")
    assert search.returncode == 2 and search.stderr.count("\n") == 1, search.stderr
    assert "runtime install" in search.stderr and "pip install anytime-explorer" in search.stderr
    assert "Traceback" not in search.stderr


def test_the_deploying_guide_gives_the_steps_this_test_takes():
    guide = (ROOT / "docs" / "guides" / "deploying.md").read_text()
    device = guide.split("## On the device", 1)[1].split("\n## ", 1)[0]
    assert "pip wheel ./runtime --no-deps -w dist/" in device
    assert "pip install anytime_explorer_runtime-" in device
    assert "explorer run winner/ " in device and "explorer curve winner/ --device tx2" in device
