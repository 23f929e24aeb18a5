"""A normal install works: the wheel carries the shipped search spaces, profiles, templates and notebook,
and the installed command finds them by name from any folder."""

import os
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_installed_elsewhere_finds_its_spaces_and_profiles(tmp_path):
    import shutil
    built, source = tmp_path / "dist", tmp_path / "source"
    # built from a copy: setuptools writes build/ and the egg-info beside the sources
    shutil.copytree(ROOT, source, symlinks=True, ignore=shutil.ignore_patterns(
        ".git", ".venv", ".cache", "build", "*.egg-info", "reports", "tests", "benchmarks", "docs", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(built)], check=True, cwd=tmp_path, capture_output=True)
    wheel = next(built.glob("anytime_explorer-*.whl"))
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # the wheel alone goes into the new environment (offline); its dependencies are read from this one,
    # appended after it on the path so that the installed wheel, not this checkout, is what runs
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
                    str(wheel)], check=True, capture_output=True)
    somewhere = tmp_path / "elsewhere"
    somewhere.mkdir()
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(tmp_path / "cache")}
    explorer = [str(python), "-m", "explorer"]

    def run(*args: str) -> str:
        done = subprocess.run(explorer + list(args), cwd=somewhere, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout

    where = subprocess.run([str(python), "-c", "import explorer; print(explorer.__file__)"], cwd=somewhere,
                           capture_output=True, text=True, check=True).stdout
    assert str(site) in where                      # the installed wheel, not the checkout
    assert "encoder_blocks" in run("space", "show", "anytime_depth")
    assert "tx2" in run("profile", "paper", "--device", "tx2")
    assert "wrote nb/analysis.ipynb" in run("notebook", "--out", "nb")   # the notebook is package data too
    assert (somewhere / "nb" / "analysis.ipynb").read_bytes() == (ROOT / "notebooks" / "analysis.ipynb").read_bytes()
    out = run("search", "--space", "tiny", "--data", "synthetic:48:16", "--train-size", "32x32", "--input-size",
              "64x64", "--batch-size", "8", "--supernet-steps", "4", "--finalists", "1", "--finalist-steps", "2",
              "--tune-steps", "1", "--trials", "3", "--timeout", "0", "--study", "wheel", "--no-report",
              "--reports", str(somewhere / "reports"))
    assert "ratio to the retrained paper-design baseline" in out
