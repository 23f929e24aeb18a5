"""The calibration probe: bundle, torch-free probe, power sensors (fake sysfs trees), resume, fit."""

import json
import os
import shutil
import subprocess
import zipfile
import sys
import tarfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from explorer import probe
from explorer.cost.precision import QUANTIZABLE_KINDS
from explorer.calibration.calibrate import fit_energy, fit_results

TINY = dict(scale=0.05, n_stage=1, repeats=2)


@pytest.fixture(scope="module")
def bundle_tar(tmp_path_factory) -> Path:
    from explorer.calibration.bundle import write_bundle
    out = tmp_path_factory.mktemp("bundle") / "probe.tar"
    write_bundle(out, **TINY)
    return out


@pytest.fixture
def bundle_dir(bundle_tar, tmp_path) -> Path:
    folder = tmp_path / "unpacked"
    with tarfile.open(bundle_tar) as tar:
        tar.extractall(folder)
    return folder


def _write(root: Path, rel: str, value) -> None:
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(f"{value}\n")


# -- sensors -------------------------------------------------------------------------------------
def test_ina3221_hwmon_reads_the_input_rail_only(tmp_path):
    dev = "sys/class/hwmon/hwmon2"
    _write(tmp_path, f"{dev}/name", "ina3221")
    for n, label, mv, ma in ((1, "VDD_IN", 5000, 2000), (2, "VDD_SYS_GPU", 5000, 500), (3, "VDD_SYS_CPU", 5000, 300)):
        _write(tmp_path, f"{dev}/in{n}_label", label)
        _write(tmp_path, f"{dev}/in{n}_input", mv)
        _write(tmp_path, f"{dev}/curr{n}_input", ma)
    _write(tmp_path, f"{dev}/in4_input", 12)   # a shunt voltage: no current beside it
    sensor = probe.find_sensor(str(tmp_path), vcgencmd=str(tmp_path / "no-vcgencmd"))
    assert sensor.name == "ina3221-hwmon" and sensor.read() == pytest.approx(10.0)
    (tmp_path / f"{dev}/in1_label").write_text("VDD_CPU_GPU_CV\n")  # no input rail: every rail, summed
    assert probe.find_sensor(str(tmp_path), "none").read() == pytest.approx(10.0 + 2.5 + 1.5)


def test_ina3221_iio_hwmon_power_and_none(tmp_path):
    assert probe.find_sensor(str(tmp_path), "none") is None
    _write(tmp_path, "sys/class/hwmon/hwmon0/name", "amdgpu")
    _write(tmp_path, "sys/class/hwmon/hwmon0/power1_input", 12_500_000)   # microwatts
    assert probe.find_sensor(str(tmp_path), "none").read() == pytest.approx(12.5)
    iio = "sys/bus/i2c/drivers/ina3221x/0-0040/iio:device0"
    for n, rail, mw in ((0, "VDD_SYS_GPU", 900), (1, "VDD_IN", 4200)):
        _write(tmp_path, f"{iio}/rail_name_{n}", rail)
        _write(tmp_path, f"{iio}/in_power{n}_input", mw)
    sensor = probe.find_sensor(str(tmp_path), "none")   # the board's rails before a generic hwmon
    assert sensor.name == "ina3221-iio" and sensor.read() == pytest.approx(4.2)


def test_rapl_counts_packages_and_handles_wraparound(tmp_path):
    wrap = 262_143_328_850
    for zone in ("intel-rapl:0", "intel-rapl:1"):
        _write(tmp_path, f"sys/class/powercap/{zone}/name", "package-" + zone[-1])
        _write(tmp_path, f"sys/class/powercap/{zone}/max_energy_range_uj", wrap)
        _write(tmp_path, f"sys/class/powercap/{zone}/energy_uj", wrap - 500_000)
    _write(tmp_path, "sys/class/powercap/intel-rapl:0:0/energy_uj", 5)    # core: inside package 0
    sensor = probe.find_sensor(str(tmp_path), "none")
    assert sensor.name == "rapl" and len(sensor.zones) == 2
    with probe.PowerWindow(sensor) as w:
        time.sleep(0.05)
        _write(tmp_path, "sys/class/powercap/intel-rapl:0/energy_uj", 1_500_000)   # wrapped: +2 J
        _write(tmp_path, "sys/class/powercap/intel-rapl:1/energy_uj", wrap - 100_000)  # +0.4 J
    assert w.watts * w.seconds == pytest.approx(2.4)


PMIC = """\
     3V7_WL_SW_A current(0)=0.10000000A
       3V3_SYS_A current(1)=0.50000000A
        DDR_VDD2_A current(4)=0.02000000A
     3V7_WL_SW_V volt(8)=3.70000000V
       3V3_SYS_V volt(9)=3.30000000V
        EXT5V_V volt(24)=5.14804000V
"""


def test_rpi5_pmic_through_an_injected_vcgencmd(tmp_path):
    assert probe.parse_pmic_adc(PMIC) == pytest.approx(0.1 * 3.7 + 0.5 * 3.3)
    script = tmp_path / "vcgencmd"
    script.write_text(f"#!/bin/sh\ncat <<'EOF'\n{PMIC}EOF\n")
    script.chmod(0o755)
    sensor = probe.find_sensor(str(tmp_path), str(script))
    assert sensor.name == "rpi5-pmic" and sensor.read() == pytest.approx(2.02)
    with pytest.raises(ValueError):
        probe.parse_pmic_adc("error=1 error_msg=\"Command not registered\"")


def test_energy_per_inference_subtracts_idle_power(tmp_path):
    dev = "sys/class/hwmon/hwmon0"
    _write(tmp_path, f"{dev}/name", "ina3221")
    _write(tmp_path, f"{dev}/in1_label", "VDD_IN")
    _write(tmp_path, f"{dev}/in1_input", 5000)
    _write(tmp_path, f"{dev}/curr1_input", 400)          # idle: 2 W
    sensor = probe.find_sensor(str(tmp_path), "none")
    idle = probe.idle_power(sensor, 0.05)
    assert idle == pytest.approx(2.0)
    _write(tmp_path, f"{dev}/curr1_input", 1400)         # busy: 7 W
    r = probe.inference_energy(sensor, lambda: time.sleep(0.01), idle, min_seconds=0.1)
    assert r["watts"] == pytest.approx(7.0) and r["runs"] >= 3
    assert r["j"] == pytest.approx(5.0 * r["ms"] / 1000.0)


def test_energy_fit_recovers_fixed_energy_and_power():
    runs = {f"c{i}": {"ms": ms, "j": 0.05 + 3.0 * ms / 1000.0} for i, ms in enumerate((5.0, 12.0, 30.0))}
    fixed, power, prov = fit_energy({"sensor": "rapl", "kind": "energy", "what": "zones package-0",
                                     "idle_w": 4.0, "inferences": runs})
    assert fixed == pytest.approx(0.05) and power == pytest.approx(3.0) and prov["energy"] == "measured"
    fixed, power, prov = fit_energy({"sensor": None, "note": "no readable power sensor"})
    assert (fixed, power, prov["energy"]) == (0.0, 0.0, "not measured") and "no readable" in prov["energy_note"]


# -- probe, resume, fit ----------------------------------------------------------------------------
def test_interrupted_probe_resumes_without_measuring_again(bundle_dir, tmp_path, monkeypatch):
    out = tmp_path / "results.json"
    monkeypatch.setattr(probe.timing, "SLOW", 1e9)   # counts calls: no window of this jittery machine re-timed
    seen = []

    def stop_after_five(i, n, what):
        seen.append(i)
        if i == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        probe.run_probe(bundle_dir, out, repeats=2, energy=False, progress=stop_after_five)
    kept = json.loads(out.read_text())
    assert len(kept["layers"]) == 5
    calls = []
    real, real_chain = probe.time_call, probe.time_chain
    monkeypatch.setattr(probe.run, "time_call", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(probe.timing, "time_call", lambda *a, **k: calls.append(1) or real(*a, **k))

    def counted_chain(fns, warmup, repeats, timed, new_round):   # a stage graph timed in its chain counts
        calls.extend(1 for on in timed if on)
        return real_chain(fns, warmup, repeats, timed, new_round)
    monkeypatch.setattr(probe.run, "time_chain", counted_chain)
    res = probe.run_probe(bundle_dir, out, repeats=2, energy=True, root=str(tmp_path), vcgencmd="none")
    total = len(res["bundle"]["layers"]) + sum(len(c["graphs"]) for c in res["bundle"]["candidates"])
    checks = len(res["speed"]["ms"]) - len(kept["speed"]["ms"])   # the machine's speed, re-timed as it went
    # each check times the layer graph and the stage graph
    assert len(calls) == total - 5 + 2 * checks and checks == 1 + (total - 6) // probe.SPEED_CHECK_EVERY + 1
    assert res["speed"]["layer"] == probe.speed_layer(res["bundle"]["layers"])["id"]
    assert res["speed"]["stage"] == probe.speed_stage(res["bundle"]["candidates"])["file"]
    assert res["speed"]["stage"].endswith("image_encoder.onnx")
    assert len(res["speed"]["stage_ms"]) == len(res["speed"]["ms"])
    assert res["speed"]["remeasured"] == 0
    assert all(res["layers"][k] == v for k, v in kept["layers"].items())
    assert res["energy"]["sensor"] is None and "no readable power sensor" in res["energy"]["note"]
    calls.clear()
    probe.run_probe(bundle_dir, out, repeats=2, energy=False)    # finished: nothing measured again
    assert calls == []
    prof = fit_results(res, name="box")
    assert prof.provenance["conditions"]["speed_drift"] == pytest.approx(probe.speed_drift(res), abs=1e-3)
    assert prof.latency_basis == "measured" and prof.energy_basis == "none"
    assert prof.provenance["provider"] == "CPUExecutionProvider" and prof.active_power_w == 0.0
    layers = res["bundle"]["layers"]
    int8 = [layer for layer in layers if layer.get("precision") == "int8"]
    # every convolution of the sweep goes in quantized too (an int8 export quantizes stage graphs whole)
    assert int8 and {layer["workload"]["kind"] for layer in int8} <= set(QUANTIZABLE_KINDS)
    # but the LiDAR encoder's, which int8 graphs keep fp32
    assert len(int8) == sum(layer["workload"]["kind"] in QUANTIZABLE_KINDS and layer["workload"]["stage"] != "lidar_encoder"
                            for layer in layers if layer not in int8)
    assert not any(layer["workload"]["stage"] == "lidar_encoder" for layer in int8)
    assert prof.provenance["fit"][0]["count"] == len(layers) - len(int8)
    # and the calibration candidate's stage graphs, quantized whole
    fp32_cands = [c for c in res["bundle"]["candidates"] if c.get("precision", "fp32") == "fp32"]
    int8_cands = [c for c in res["bundle"]["candidates"] if c.get("precision") == "int8"]
    assert len(int8_cands) == len(fp32_cands) == 1 and int8_cands[0]["key"] == fp32_cands[0]["key"] + "-int8"
    assert prof.provenance["fit"][1]["count"] == len(fp32_cands[0]["graphs"])
    # the quantized graphs give the profile its int8 section
    assert prof.precisions == ("fp32", "int8") and prof.int8.provenance["fit"][0]["count"] == len(int8)
    assert prof.int8.provenance["fit"][1]["count"] == len(int8_cands[0]["graphs"])
    assert prof.int8.stage_overhead_ms == prof.stage_overhead_ms


def test_graphs_timed_while_the_machine_ran_slow_are_timed_again(bundle_dir, tmp_path, monkeypatch, run_cli):
    """The probe re-times one fixed graph every SPEED_CHECK_EVERY graphs; the graphs between two
    checks of which one ran slow are timed again, and the profile says so."""
    # each check times the layer graph, then the stage graph; the third: another load had slowed both
    checks = iter([1.0, 1.0, 1.0, 1.0, 3.0, 3.0] + [1.0] * 1000)
    timed = []

    def fake_time_call(fn, warmup, repeats):
        if repeats == probe.SPEED_CHECK_REPEATS:
            return next(checks)
        timed.append(1)
        return 2.0

    monkeypatch.setattr(probe.run, "time_call", fake_time_call)

    monkeypatch.setattr(probe.timing, "time_call", fake_time_call)
    monkeypatch.setattr(probe.run, "time_chain", _graph_by_graph(fake_time_call))
    logged, shown = [], []
    res = probe.run_probe(bundle_dir, tmp_path / "r.json", repeats=2, energy=False, log=logged.append,
                          progress=lambda i, n, what: shown.append((what, i, n)))
    total = len(res["bundle"]["layers"]) + sum(len(c["graphs"]) for c in res["bundle"]["candidates"])
    every = probe.SPEED_CHECK_EVERY
    assert total > 3 * every
    # the progress counts the pass of timing again on its own, over the graphs it times again
    assert _passes(shown) == [(probe.TIMING_GRAPHS, total), (probe.TIMING_AGAIN, 2 * every)]
    # the windows on both sides of the slow check: graphs 13-24 and 25-36, timed twice
    assert res["speed"]["remeasured"] == 2 * every and len(timed) == total + 2 * every
    assert probe.speed_drift(res) == pytest.approx(2.0)
    assert any("timing those again" in line for line in logged) and any("changed by 200%" in line for line in logged)
    # explorer calibrate times its slow graphs once more: no second note of the speed, no scratch path resumed
    more = []
    probe.run_probe(bundle_dir, tmp_path / "r.json", repeats=2, energy=False, log=more.append, remeasure_passes=0,
                    again=True)
    assert not any("changed by" in line or "resuming" in line or str(tmp_path) in line for line in more), more
    assert probe.slow_windows([1.0, 1.0, 1.05, 1.2, 1.0]) == [2, 3]
    # a machine slowed for most of the run: its usual speed is still the undisturbed one
    assert probe.usual_speed([1.0, 1.02, 1.4, 1.4, 1.4, 1.4, 1.41, 1.0, 1.45, 1.4]) == pytest.approx(1.0)
    out = tmp_path / "r.json"
    code, stdout, err = run_cli("calibrate", "--fit", out, "--out", tmp_path / "box.yaml")
    assert code == 0, err
    assert "varied by 200%" in stdout and f"{2 * every} graphs timed while it ran slow were timed again" in stdout
    cond = yaml.safe_load((tmp_path / "box.yaml").read_text())["provenance"]["conditions"]
    assert cond["speed_drift"] == 2.0 and cond["speed_remeasured"] == 2 * every
    res["speed"] = {"layer": res["speed"]["layer"], "ms": [1.0, 1.05], "remeasured": 0}
    out.write_text(json.dumps(res))
    code, stdout, _ = run_cli("calibrate", "--fit", out, "--out", tmp_path / "box.yaml", "--force")
    assert code == 0 and "varied by 5%" in stdout and "timed again" not in stdout and "calibrate again" not in stdout


def _passes(calls: list[tuple[str, int, int | None]]) -> list[tuple[str, int]]:
    """The passes that progress calls (what, done, total) tell of, as [(what, total)]: each starts at
    0 and counts up to its total (None until it is known), under one name."""
    passes: list[list] = []
    for what, done, total in calls:
        if done == 0:
            passes.append([what, total, 0])
            continue
        last = passes[-1]
        assert what == last[0] and last[2] < done <= total and last[1] in (None, total), (what, done, total, last)
        last[1:] = [total, done]
    assert all(done == total for _, total, done in passes), passes
    return [(what, total) for what, total, _ in passes]


def _graph_count(bundle_dir) -> int:
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    return len(manifest["layers"]) + sum(len(c["graphs"]) for c in manifest["candidates"])


def _kept_timings(res: dict) -> list[float]:
    return list(res["layers"].values()) + [ms for st in res["stages"].values() for ms in st.values()]


@pytest.mark.parametrize("later_ms", [5.0, 1.5])
def test_a_slow_stage_check_alone_retimes_and_the_faster_timing_is_kept(bundle_dir, tmp_path, monkeypatch, later_ms):
    """The large convolution ran at its usual speed while the stage graph ran slow (small operators
    suffer more from another load): that window is timed again, and of a graph's two timings the
    faster one stays."""
    checks = iter([1.0, 1.0, 1.0, 1.0, 1.0, 2.0] + [1.0] * 1000)
    timed = []

    def fake_time_call(fn, warmup, repeats):
        if repeats == probe.SPEED_CHECK_REPEATS:
            return next(checks)
        timed.append(1)
        return 2.0 if len(timed) <= total else later_ms

    total = _graph_count(bundle_dir)
    monkeypatch.setattr(probe.run, "time_call", fake_time_call)
    monkeypatch.setattr(probe.timing, "time_call", fake_time_call)
    monkeypatch.setattr(probe.run, "time_chain", _graph_by_graph(fake_time_call))
    res = probe.run_probe(bundle_dir, tmp_path / "r.json", repeats=2, energy=False)
    every = probe.SPEED_CHECK_EVERY
    assert res["speed"]["remeasured"] == 2 * every and len(timed) == total + 2 * every
    # the stage graph's 2x counts in the speed change, the convolution's time stayed
    assert probe.speed_drift(res) == pytest.approx(1.0) and max(res["speed"]["ms"]) == 1.0
    kept = _kept_timings(res)
    assert len(kept) == total and kept.count(min(2.0, later_ms)) >= 2 * every and res["earlier"] == {}
    assert sorted(kept)[-1] == 2.0


def test_a_machine_slow_for_the_whole_first_pass_is_found_out_once_it_speeds_up(bundle_dir, tmp_path, monkeypatch):
    """Slowed by another load for the whole first pass, the checks look usual but for one spike:
    only its windows are timed again. That second pass runs at full speed, and then every graph
    of the first pass is judged slow against it and timed again too."""
    total = _graph_count(bundle_dir)
    timed, checks = [], []

    def fake_time_call(fn, warmup, repeats):
        first_pass = len(timed) < total
        if repeats == probe.SPEED_CHECK_REPEATS:
            checks.append(1)
            return (3.0 if len(checks) in (5, 6) else 2.0) if first_pass else 1.0
        timed.append(1)
        return 5.0 if first_pass else 1.0

    monkeypatch.setattr(probe.run, "time_call", fake_time_call)

    monkeypatch.setattr(probe.timing, "time_call", fake_time_call)
    monkeypatch.setattr(probe.run, "time_chain", _graph_by_graph(fake_time_call))
    res = probe.run_probe(bundle_dir, tmp_path / "r.json", repeats=2, energy=False)
    every = probe.SPEED_CHECK_EVERY
    assert len(timed) == 2 * total and res["speed"]["remeasured"] == total
    kept = _kept_timings(res)
    assert len(kept) == total and set(kept) == {1.0}
    assert total > 3 * every


def _graph_by_graph(time_call):
    """A stand-in for probe.time_chain that asks ``time_call`` for each graph it times, in order."""
    def time_chain(fns, warmup, repeats, timed, new_round):
        return [time_call(fn, warmup, repeats) if on else None for fn, on in zip(fns, timed)]
    return time_chain


def test_bundle_int8_graphs_are_quantized_convolutions_and_stage_graphs(bundle_dir):
    import onnx
    manifest = probe.load_manifest(bundle_dir)
    int8 = [layer for layer in manifest.layers if layer.get("precision") == "int8"]
    ops = {n.op_type for n in onnx.load(str(bundle_dir / int8[0]["file"])).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "Conv"} <= ops
    cand = next(c for c in manifest.candidates if c.get("precision") == "int8")
    # its deployed stage graphs, as an export groups them: the first runs the encoders up to exit 0
    encoder = cand["graphs"][0]
    assert "image_encoder" in encoder["stage"].split("+") and encoder["stage"].split("+")[-1].startswith("exit")
    nodes = onnx.load(str(bundle_dir / encoder["file"])).graph.node
    made_by = {o: n for n in nodes for o in n.output}
    convs = [n for n in nodes if n.op_type == "Conv"]
    lidar = [c for c in convs if c.name.startswith("/lidar_encoder/")]
    assert lidar and not any(c.input[1] in made_by for c in lidar)   # kept fp32: weights read straight from initializers
    rest = [c for c in convs if c not in lidar]
    assert rest and all(made_by[c.input[0]].op_type == "DequantizeLinear" for c in rest)   # quantized whole
    # the graphs hand each other uint8 tensors, as the runtime does between int8 graphs: no quantize or
    # dequantize at those edges, and the chain runs
    graphs = [onnx.load(str(bundle_dir / g["file"])).graph for g in cand["graphs"]]
    floats = {"image", "scan", "lidar", "scan_fill"}   # inputs, and what fp32 stages (the LiDAR's) make
    handed = {i.name for g in graphs[1:] for i in g.input} - floats
    assert any(n.startswith("x") for n in handed) and any(n.startswith("skip") for n in handed)
    assert all(i.type.tensor_type.elem_type == onnx.TensorProto.UINT8 for g in graphs[1:] for i in g.input
               if i.name in handed)
    assert all(o.type.tensor_type.elem_type == onnx.TensorProto.UINT8 for g in graphs for o in g.output
               if o.name in handed)
    assert not any(n.op_type == "QuantizeLinear" and n.input[0] in handed for g in graphs[1:] for n in g.node)
    env = probe.candidate_inputs(manifest, np.random.default_rng(0), cand)
    for g in cand["graphs"]:
        sess = probe.session(bundle_dir / g["file"])
        feeds = {i.name: env[i.name] for i in sess.get_inputs()}
        env.update(zip([o.name for o in sess.get_outputs()], sess.run(None, feeds)))
    assert {env[n].dtype for n in handed} == {np.dtype(np.uint8)}


def test_probe_with_a_power_sensor_writes_measured_energy(bundle_dir, tmp_path):
    _write(tmp_path, "sys/class/hwmon/hwmon0/name", "acpi_power")
    _write(tmp_path, "sys/class/hwmon/hwmon0/power1_input", 6_000_000)
    res = probe.run_probe(bundle_dir, tmp_path / "r.json", repeats=2, root=str(tmp_path), idle_s=0.05,
                          window_s=0.05)
    e = res["energy"]
    assert e["sensor"] == "hwmon-power" and e["idle_w"] == pytest.approx(6.0)
    assert set(e["inferences"]) == {c["key"] for c in res["bundle"]["candidates"]}
    prof = fit_results(res)
    assert prof.provenance["energy"] == "measured" and prof.energy_basis == "measured"
    assert prof.provenance["energy_sensor"]["sensor"] == "hwmon-power"


def test_foreign_or_truncated_results_are_one_line_exit_2(bundle_dir, tmp_path, run_cli):
    out = tmp_path / "r.json"
    probe.run_probe(bundle_dir, out, repeats=2, energy=False, remeasure_passes=0)   # results to spoil, not timings
    text = out.read_text()
    (tmp_path / "cut.json").write_text(text[: len(text) // 2])
    code, _, err = run_cli("calibrate", "--fit", tmp_path / "cut.json", "--out", tmp_path / "p.yaml")
    assert code == 2 and "truncated" in err and len(err.strip().splitlines()) == 1
    old = json.loads(text)
    old["version"] = 0
    (tmp_path / "old.json").write_text(json.dumps(old))
    code, _, err = run_cli("calibrate", "--fit", tmp_path / "old.json", "--out", tmp_path / "p.yaml")
    assert code == 2 and "format v0" in err and len(err.strip().splitlines()) == 1
    other = dict(old, version=probe.VERSION, bundle=dict(old["bundle"], id="0123456789abcdef"))
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert probe.main(["--bundle", str(bundle_dir), "--out", str(tmp_path / "other.json"), "--no-energy"]) == 2
    assert probe.main(["--bundle", str(bundle_dir), "--out", str(tmp_path / "x.json"),
                       "--provider", "NoSuchExecutionProvider"]) == 2
    code, _, err = run_cli("calibrate", "--fit", out, "--out", tmp_path / "p.yaml")
    assert code == 0, err
    data = yaml.safe_load((tmp_path / "p.yaml").read_text())
    assert data["provenance"]["latency"] == "measured" and data["provenance"]["conditions"]["bundle"]


def test_unknown_provider_is_one_line_exit_2(run_cli, tmp_path):
    for args in (("calibrate", "--out", tmp_path / "p.yaml"), ("run", tmp_path, "--image", "x.png",
                                                                 "--scan", "s.csv", "--deadline", "5ms")):
        code, _, err = run_cli(*args, "--provider", "NoSuchExecutionProvider")
        assert code == 2 and "NoSuchExecutionProvider" in err and len(err.strip().splitlines()) == 1


def test_devices_say_what_each_profile_rests_on(run_cli):
    code, out, _ = run_cli("devices", "--json")
    rows = {r["name"]: r for r in json.loads(out)}
    assert code == 0
    assert (rows["tx2"]["latency"], rows["tx2"]["energy"]) == ("published", "published")
    assert (rows["tx2-cpu"]["energy"], rows["orin-nano"]["latency"]) == ("none", "estimate")


# -- the probe where only numpy and onnxruntime exist ----------------------------------------------
def _bare_venv(where: Path) -> Path:
    """A venv with numpy and onnxruntime only (the versions installed here, from pip's usual
    sources); skips the test when pip cannot install them."""
    import numpy
    import onnxruntime
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(where)], check=True)
    py = where / "bin" / "python"
    pip = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--quiet",
                          "--disable-pip-version-check", f"numpy=={numpy.__version__}",
                          f"onnxruntime=={onnxruntime.__version__}"], capture_output=True, text=True)
    if pip.returncode != 0:
        pytest.skip(f"could not install numpy and onnxruntime into a fresh venv: {pip.stderr.strip()[-200:]}")
    return py


@pytest.mark.slow
def test_probe_runs_with_only_numpy_and_onnxruntime(bundle_tar, tmp_path, run_cli):
    py = _bare_venv(tmp_path / "venv")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    torch = subprocess.run([str(py), "-c", "import torch"], capture_output=True, env=env)
    assert torch.returncode != 0, "the bare venv must not see torch"
    device = tmp_path / "device"
    device.mkdir()
    shutil.copy(bundle_tar, device)
    subprocess.run(["tar", "xf", bundle_tar.name], cwd=device, check=True)
    with zipfile.ZipFile(device / "probe.pyz") as zf:   # the probe package, whole, as a zip application
        assert sorted(zf.namelist()) == ["__main__.py"] + sorted(
            f"probe/{p.name}" for p in Path(probe.__file__).parent.glob("*.py"))
    sysfs = tmp_path / "fake-sysfs"
    _write(sysfs, "sys/class/powercap/intel-rapl:0/energy_uj", 1000)
    run = subprocess.run([str(py), "probe.pyz", "--out", "results.json", "--sysfs-root", str(sysfs),
                          "--idle", "0.05", "--window", "0.05"], cwd=device, capture_output=True, text=True,
                         env=env, timeout=120)
    assert run.returncode == 0, run.stderr
    res = json.loads((device / "results.json").read_text())
    assert res["device"]["onnxruntime"] and res["device"]["provider"] == "CPUExecutionProvider"
    assert res["energy"]["sensor"] == "rapl" and len(res["layers"]) == len(res["bundle"]["layers"])
    code, _, err = run_cli("calibrate", "--fit", device / "results.json", "--out", tmp_path / "board.yaml")
    assert code == 0, err
    code, out, _ = run_cli("profile", "paper", "--device", tmp_path / "board.yaml", "--json")
    assert code == 0 and json.loads(out)["paths"][1]["latency_ms"] > 0


@pytest.mark.slow
def test_calibration_times_again_the_graphs_far_above_its_fit(tmp_path, monkeypatch):
    """A graph slowed between two speed checks (so that neither shows it) sits far above the fit of
    all the others: calibrate times it again and keeps the faster timing. A graph that is as slow the
    second time is not timed a third."""
    from explorer.calibration import calibrate as cal
    real_probe, real_set_aside, calls, inflated, stubborn, set_aside = probe.run_probe, probe.set_aside, [], {}, {}, []
    normal = {}

    def probe_with_a_slowed_spell(folder, out, *args, **kwargs):
        res = real_probe(folder, out, *args, **kwargs)
        calls.append((args[3], kwargs.get("remeasure_passes")))   # energy: measured the first time only
        if len(calls) == 1:   # one stage graph of the first run took 20x its time, another always does
            key = next(iter(res["stages"]))
            first, second = list(res["stages"][key])[:2]
            normal[f"{key}/{first}"] = res["stages"][key][first]
            res["stages"][key][first] *= 20
            inflated[f"{key}/{first}"] = res["stages"][key][first]
            stubborn[f"{key}/{second}"] = res["stages"][key][second] * 20
        else:   # timed again: its first time, whatever this machine's load does to the real one
            for label, ms in normal.items():
                key, _, stage = label.partition("/")
                if stage in res["stages"].get(key, {}):
                    res["stages"][key][stage] = ms
        for label, ms in stubborn.items():
            key, _, stage = label.partition("/")
            res["stages"][key][stage] = ms
        probe.write_atomically(Path(out), res)
        return res

    class Probe:   # the probe module as calibrate sees it (the probe's own re-timing keeps the real one)
        run_probe = staticmethod(probe_with_a_slowed_spell)

        @staticmethod
        def set_aside(res, labels):
            set_aside.append(list(labels))
            real_set_aside(res, labels)

        def __getattr__(self, name):
            return getattr(probe, name)

    monkeypatch.setattr(cal, "_probe", Probe())
    logged, shown = [], []
    prof = cal.calibrate(repeats=2, scale=0.05, stage_candidates=1, energy=False, results_out=tmp_path / "r.json",
                         log=logged.append, progress=lambda *call: shown.append(call))
    res = json.loads((tmp_path / "r.json").read_text())
    assert len(calls) >= 2 and calls[1] == (False, 0)   # a round of its own is the second timing
    assert prof.provenance["conditions"]["retimed_outliers"] >= len(inflated) == 1
    assert any("timing those again" in line for line in logged)
    for label, ms in inflated.items():
        key, _, stage = label.partition("/")
        assert res["stages"][key][stage] < ms / 4   # timed again, the faster kept
    assert [label in labels for labels in set_aside for label in stubborn] == [True] + [False] * (len(set_aside) - 1)
    # every phase counted from 0 to its own total: the rounds of timing again over the graphs they time
    passes = _passes(shown)
    graphs = len(res["bundle"]["layers"]) + sum(len(c["graphs"]) for c in res["bundle"]["candidates"])
    assert passes[0][0] == cal.EXPORTING and passes[0][1] > 0 and passes[1] == (probe.TIMING_GRAPHS, graphs)
    rounds = [n for (what, n), (before, _) in zip(passes[1:], passes)
              if what == probe.TIMING_AGAIN and before == cal.FITTING]
    assert rounds == [len(labels) for labels in set_aside] and passes[-1] == (cal.FITTING, 1)


def test_graphs_made_here_carry_their_opsets_ir_version(monkeypatch):
    # onnx's newest IR version (14 in onnx 1.23) is refused by an older onnxruntime (1.30 reads 13)
    import onnx
    from explorer.probe import sessions
    seen = []
    real = sessions._session
    monkeypatch.setattr(sessions, "_session", lambda model, *a: (seen.append(onnx.load_from_string(model)),
                                                                 real(model, *a))[1])
    monkeypatch.setattr(sessions, "_POOL", {})
    sessions.block_size()
    assert [m.ir_version for m in seen] == [8]


def test_the_wait_for_a_calm_machine_reads_its_limit_when_called(monkeypatch):
    """The limit is read when the wait starts, not when the module was imported: the tests set it to
    0 (conftest), a user's probe keeps its minute, and a run_probe or calibrate call without one uses it."""
    from explorer.probe import timing
    timed = []

    def still_slow() -> float:
        timed.append(1)
        return 10.0

    assert timing.wait_until_calm(10.0, still_slow, usual=1.0) == 10.0 and timed == []   # 0 s: no second timing
    monkeypatch.setattr(timing.time, "sleep", lambda s: None)
    clock = iter(range(100))   # a second passes at each look at the clock: the start, then once a timing
    monkeypatch.setattr(timing.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(timing, "CALM_WAIT_S", 3.0)
    assert timing.wait_until_calm(10.0, still_slow, usual=1.0) == 10.0 and len(timed) == 2
