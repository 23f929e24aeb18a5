"""``explorer calibrate``'s arguments: every mistake in a name or an output path is one line, exit 2,
before the minute of exporting graphs (or the fit) starts, and nothing is made. The work itself is
replaced by functions that fail the test if reached, so these run in a moment."""

from __future__ import annotations

import pytest

import explorer.calibration.bundle
import explorer.calibration.calibrate
from explorer.errors import UserError


def _work_started(*args, **kwargs):
    pytest.fail("calibrate went on to its work")


@pytest.fixture
def calibrate_cli(run_cli, monkeypatch, tmp_path, tmp_path_factory):
    """Runs ``explorer calibrate ARGS`` in ``tmp_path`` with the work stubbed out; returns (code, stderr)
    after checking that the files in ``tmp_path`` are the ones there before."""
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path_factory.mktemp("cache")))
    monkeypatch.chdir(tmp_path)
    for module, name in ((explorer.calibration.bundle, "write_bundle"),
                         (explorer.calibration.bundle, "write_bundle_dir"),
                         (explorer.calibration.calibrate, "calibrate"),
                         (explorer.calibration.calibrate, "read_results"),
                         (explorer.calibration.calibrate, "fit_results")):
        monkeypatch.setattr(module, name, _work_started)

    def run(*args: str) -> tuple[int, str]:
        before = sorted(tmp_path.rglob("*"))
        code, _, err = run_cli("calibrate", *args)
        assert sorted(tmp_path.rglob("*")) == before, "calibrate made or removed files"
        return code, err
    return run


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("args, says", [
    (["--name", "a b/c", "--out", "p.yaml"], ["--name 'a b/c' is not a plain name", "letters, digits"]),
    (["--name", "", "--out", "p.yaml", "--fit", "x.json"], ["--name '' is not a plain name"]),
    (["--out", "my box.yaml"], ["would be named 'my box'", "give --name a plain name"]),
    (["--name", "tx2", "--out", "p.yaml"], ["'tx2' is a built-in device profile's name", "rpi4",
                                            "choose another name"]),
    # a case-blind file system finds the built-in under this name as well
    (["--name", "TX2-CPU", "--out", "p.yaml", "--quick"], ["built-in device profile's name"]),
    (["--out", "rpi4.yaml"], ["--out rpi4.yaml: the profile would be named 'rpi4'", "e.g. --name rpi4-measured"]),
])
def test_a_name_that_is_not_plain_or_is_a_built_in_s_is_refused_before_any_work(calibrate_cli, args, says):
    code, err = calibrate_cli(*args)
    line = _one_line(err)
    assert code == 2 and all(s in line for s in says), line


@pytest.mark.parametrize("args, says", [
    (["--bundle", "b.zip"], ["--bundle b.zip", "gzip-compressed tar", "ending in .tar, .tar.gz or .tgz"]),
    (["--out", "x.txt"], ["--out x.txt", "is YAML", "ending in .yaml or .yml"]),
    (["--out", "x.txt", "--fit", "x.json"], ["ending in .yaml or .yml"]),
])
def test_an_output_with_the_wrong_suffix_is_refused_before_any_work(calibrate_cli, args, says):
    code, err = calibrate_cli(*args)
    line = _one_line(err)
    assert code == 2 and all(s in line for s in says), line


@pytest.mark.parametrize("args, flag, ending", [
    (["--bundle", "victim"], "--bundle", ".tgz"),
    (["--bundle", "victim", "--force", "--quick"], "--bundle", ".tgz"),
    (["--bundle", "victim.tar", "--force"], "--bundle", ".tgz"),
    (["--out", "victim"], "--out", ".yml"),
    (["--out", "victim.yaml", "--force"], "--out", ".yml"),
    (["--out", "victim", "--fit", "x.json"], "--out", ".yml"),
])
def test_a_folder_in_the_output_s_place_is_refused_without_suggesting_force(calibrate_cli, tmp_path, args, flag,
                                                                            ending):
    # --force cannot overwrite a folder: the write would fail after the work, so say so first
    (tmp_path / args[1]).mkdir()
    (tmp_path / args[1] / "kept").write_text("mine")
    code, err = calibrate_cli(*args)
    line = _one_line(err)
    assert code == 2 and f"{args[1]}: is a folder; give {flag} a file name ending in" in line, line
    assert ending in line and "--force" not in line
    assert (tmp_path / args[1] / "kept").read_text() == "mine"


def test_an_existing_file_still_asks_for_force(calibrate_cli, tmp_path):
    (tmp_path / "b.tar").write_text("old")
    code, err = calibrate_cli("--bundle", "b.tar")
    assert code == 2 and "b.tar exists: pass --force to overwrite it" in _one_line(err)
    assert (tmp_path / "b.tar").read_text() == "old"


@pytest.mark.parametrize("args, reached, expected", [
    (["--bundle", "probe.tar"], "write_bundle", "probe.tar"),
    (["--bundle", "sub/probe.tar.gz"], "write_bundle", "sub/probe.tar.gz"),
    (["--bundle", "probe.tgz"], "write_bundle", "probe.tgz"),
    (["--out", "box.yml", "--name", "box-2.0_a"], "calibrate", "box-2.0_a"),
    (["--out", "sub/jetson-orin.yaml"], "calibrate", "jetson-orin"),
])
def test_good_names_reach_the_work(calibrate_cli, monkeypatch, args, reached, expected):
    # the checks refuse only mistakes: these go on to the work (stubbed to stop there, with what it was given)
    def stop(*a, **k):
        raise UserError(f"reached {reached} with {k.get('name', a[0] if a else None)}")
    module = explorer.calibration.bundle if reached == "write_bundle" else explorer.calibration.calibrate
    monkeypatch.setattr(module, reached, stop)
    code, err = calibrate_cli(*args)
    assert code == 2 and _one_line(err) == f"explorer: error: reached {reached} with {expected}"


@pytest.mark.parametrize("args, says", [
    (["--bundle", "b.tar", "--out", "p.yaml"], "--out: not read with --bundle"),
    (["--bundle", "b.tar", "--name", "box"], "--name: not read with --bundle"),
    (["--fit", "r.json", "--out", "p.yaml", "--quick"], "--quick: not read with --fit"),
    (["--fit", "r.json", "--out", "p.yaml", "--threads", "2", "--no-energy"], "--threads, --no-energy: not read"),
    (["--fit", "r.json", "--out", "p.yaml", "--repeats", "5"], "--repeats: not read with --fit"),
])
def test_an_option_the_chosen_way_would_ignore_is_refused(calibrate_cli, args, says):
    code, err = calibrate_cli(*args)
    line = _one_line(err)
    assert code == 2 and says in line, line
