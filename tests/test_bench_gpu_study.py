"""The gpu suite's bench_gpu_study: what it reads off a study."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name, option", [("gpu_study", "--time-limit")])
def test_they_say_what_they_measure(name, option):
    proc = subprocess.run([sys.executable, "-m", "benchmarks.gpu", "--only", name, "--help"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert option in proc.stdout and "--worker" not in proc.stdout


def test_phases_are_placed_on_the_clock_the_study_recorded():
    from benchmarks.gpu import phase_spans
    started = time.mktime(time.strptime("2026-11-28 10:00:00", "%Y-%m-%d %H:%M:%S"))
    run = {"started": "2026-11-28 10:00:00", "seconds": 100.0,
           "phases": {"data": 10.0, "measuring": 5.0, "supernet": 35.0, "sampling": 30.0, "finalists": 20.0}}
    spans = phase_spans(run, search_end=started + 104.0, export_s=6.0)
    assert list(spans) == ["data", "measuring", "supernet", "sampling", "finalists", "report", "export"]
    assert spans["supernet"] == (started + 15.0, started + 50.0)
    assert spans["finalists"] == (started + 80.0, started + 100.0)
    assert spans["report"] == (started + 100.0, started + 104.0) and spans["export"] == (started + 104.0, started + 110.0)


def test_the_export_gap_is_the_worst_path():
    from benchmarks.gpu import export_gap
    from explorer.deploy.manifest import Manifest, Source
    manifest = Manifest.model_construct(path_metrics=[{"rmse": 0.50}, {"rmse": 0.40}],
                                        source=Source(study_path_metrics=[{"rmse": 0.50}, {"rmse": 0.43}]))
    assert export_gap(manifest) == pytest.approx(0.03)
