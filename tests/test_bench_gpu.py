"""The gpu suite's bench_gpu answers --help and runs a tiny configuration on the CPU (where CI runs)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ["-m", "benchmarks.gpu", "--only", "gpu"]


def test_it_says_what_it_measures():
    proc = subprocess.run([sys.executable, *BENCH, "--help"], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "--device" in proc.stdout and "--search-seconds" in proc.stdout and "--worker" not in proc.stdout


def test_without_a_gpu_utilisation_is_not_read():
    from benchmarks.gpu import Utilisation
    with Utilisation(None) as util:
        assert util.source is None and util.take() is None


@pytest.mark.slow
def test_a_tiny_configuration_runs_on_the_cpu_and_writes_its_record(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANYTIME_EXPLORER_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, *BENCH, "--device", "cpu", "--steps", "3", "--large-size", "32x32",
                           "--large-batch", "8", "--search-seconds", "4", "--search-supernet-steps", "2",
                           "--amp-steps", "1", "--warmup-steps", "1", "--data", "synthetic:32:16", "--reps", "1",
                           "--results", str(tmp_path)],
                          capture_output=True, text=True, timeout=900, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    record = json.loads(next((tmp_path / "bench_gpu").glob("*.json")).read_text())
    figures = {f["name"]: f["median"] for f in record["figures"]}
    assert {"step_s_default", "step_s_large", "two_process_speedup", "candidates_per_minute", "evaluator_share",
            "amp_loss_ratio"} <= set(figures)
    assert 0 < figures["evaluator_share"] <= 1 and figures["candidates_per_minute"] > 0
    assert "gpu_util_default" not in figures     # no GPU here: utilisation is "n/a", not a number


def test_utilisation_is_read_from_the_gpu_pytorch_trains_on(monkeypatch):
    from benchmarks.gpu import physical_index
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,1")
    assert (physical_index(0), physical_index(1)) == (3, 1)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert physical_index(0) == 0
