import json
import threading
from collections.abc import Callable

import numpy as np
import pytest
import torch

from explorer.deploy.export import export_from_checkpoint, export_network
from explorer.model import build_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.space import SearchSpace, paper_candidate
from explorer.training.train import TrainConfig, save_checkpoint

CAND = list(SearchSpace.from_yaml("tiny").enumerate())[-1]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("model")
    torch.manual_seed(0)
    net = build_network(CAND)
    export_network(net, out, (32, 48))
    return out, net


def test_export_matches_torch_on_every_path(exported):
    out, net = exported
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["verification"]["max_abs_diff"] <= 1e-4
    assert manifest["paths"] == CAND.num_paths and manifest["input_size"] == [32, 48]
    assert [s["path"] for s in manifest["stages"] if s["path"] is not None] == list(range(CAND.num_paths))
    assert {"tx2", "rpi4"} <= set(manifest["expected_cost"])
    runner = AnytimeRunner(out)
    img = np.random.default_rng(0).random((3, 32, 48), dtype=np.float32)
    scan = np.linspace(1, 4, 48, dtype=np.float32)
    res = runner.run(img, scan)
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(img)[None], torch.from_numpy(scan)[None])
    assert res.path == CAND.num_paths - 1
    assert np.abs(res.depth - ref[-1][0, 0].numpy()).max() <= 1e-4


def test_paper_design_export_verified(tmp_path):
    m = export_network(build_network(paper_candidate()), tmp_path, (224, 224), devices=("tx2",))
    assert m.verification.max_abs_diff <= 1e-4
    # path 0, then one graph per exit: encoders+ECU+exit, decoder 1+exit, decoder 2+exit, decoders 3-4+exit
    assert [s.path for s in m.stages] == [0, 1, 2, 3, 4]
    assert m.stages[4].stages == ["decoder_3", "decoder_4", "exit_4"]


def test_deadlines_and_halt(exported):
    out, _ = exported
    runner = AnytimeRunner(out)
    img, scan = np.zeros((3, 32, 48), np.float32), np.ones(48, np.float32)
    zero = runner.run(img, scan, deadline_ms=0)
    assert zero.path == 0 and np.allclose(zero.depth, 1.0)
    assert runner.run(img, scan, deadline_ms=10_000).path == CAND.num_paths - 1

    def halt_at_first_exit(path, ready):
        if path == 1:
            t = threading.Thread(target=runner.halt)
            t.start()
            t.join()
    res = runner.run(img, scan, on_path=halt_at_first_exit)
    assert res.halted and res.path == 1


def test_a_path_less_accurate_than_one_already_ready_is_never_returned(exported, tmp_path, run_cli):
    import json
    import shutil
    out, _ = exported
    shutil.copytree(out, tmp_path / "m")
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    # as measured: the last path less accurate than the one before it
    errors = [0.9, 0.5, 0.4, 0.45][:CAND.num_paths]
    manifest["path_metrics"] = [{"rmse": e} for e in errors]
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(manifest))
    runner = AnytimeRunner(tmp_path / "m")
    res = runner.run(np.zeros((3, 32, 48), np.float32), np.ones(48, np.float32), deadline_ms=10_000)
    assert [p for p, _ in res.completed] == list(range(CAND.num_paths)) and res.path == CAND.num_paths - 2
    np.save(tmp_path / "scan.npy", np.ones(48, np.float32))
    from PIL import Image
    Image.fromarray(np.zeros((32, 48, 3), np.uint8)).save(tmp_path / "frame.png")
    code, text, err = run_cli("run", tmp_path / "m", "--image", tmp_path / "frame.png", "--scan",
                              tmp_path / "scan.npy", "--deadline", "10s")
    assert code == 0, err
    assert f"returned path {CAND.num_paths - 2}" in text and "less accurate than path" in " ".join(text.split())


def test_export_from_checkpoint(tmp_path):
    net = build_network(CAND)
    save_checkpoint(tmp_path / "c.pt", net, TrainConfig(input_size=(32, 32)), 1)
    m = export_from_checkpoint(tmp_path / "c.pt", tmp_path / "out")
    assert m.input_size == (32, 32) and (tmp_path / "out" / m.stages[1].file).is_file()


def test_a_checkpoint_is_exported_and_evaluated_on_the_data_it_was_trained_on(tmp_path, run_cli):
    """Without --data, a checkpoint's export and evaluation measure the frames of the data it was trained
    on (a robot's own recording, not the generated scenes); data this machine cannot read is one line."""
    data = "synthetic:12:6"
    ck = tmp_path / "ck.pt"
    code, _, err = run_cli("train", "paper", "--data", data, "--steps", "1", "--batch-size", "2", "--train-size",
                           "32x32", "--out", ck)
    assert code == 0, err
    code, out, err = run_cli("evaluate", ck, "--frames", "2")
    assert code == 0 and f"on {data} (val)" in " ".join(out.split()), out + err
    code, _, err = run_cli("export", "--checkpoint", ck, "--out", tmp_path / "model")
    assert code == 0, err
    manifest = json.loads((tmp_path / "model" / "manifest.json").read_text())
    assert manifest["measured"]["data"] == data and manifest["curve_frames"]["data"] == data
    state = torch.load(ck, weights_only=True)
    state["data"] = f"rosbag:{tmp_path / 'gone.bag'}"
    torch.save(state, tmp_path / "moved.pt")
    for args in (["export", "--checkpoint", tmp_path / "moved.pt", "--out", tmp_path / "other"],
                 ["evaluate", tmp_path / "moved.pt"]):
        code, _, err = run_cli(*args)
        assert code == 2 and "was trained on 'rosbag:" in err and err.strip().endswith("give --data"), err
        assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "other").exists()


def test_run_cli_and_bad_inputs(exported, tmp_path, run_cli):
    from PIL import Image
    out, _ = exported
    Image.fromarray(np.zeros((32, 48, 3), np.uint8)).save(tmp_path / "ok.png")
    Image.fromarray(np.zeros((40, 48, 3), np.uint8)).save(tmp_path / "big.png")
    np.save(tmp_path / "scan.npy", np.full(48, 2.0, np.float32))
    (tmp_path / "short.csv").write_text(",".join(["2.0"] * 40))
    code, o, e = run_cli("run", out, "--image", tmp_path / "ok.png", "--scan", tmp_path / "scan.npy",
                         "--deadline", "0.001ms", "--out", tmp_path / "d.png", "--json")
    assert code == 0 and json.loads(o)["path"] == 0
    assert np.asarray(Image.open(tmp_path / "d.png")).max() == 2000  # 16-bit millimetres
    for args, msg in ((("--image", tmp_path / "big.png", "--scan", tmp_path / "scan.npy"), "the model takes"),
                      (("--image", tmp_path / "ok.png", "--scan", tmp_path / "short.csv"), "one per image column"),
                      (("--image", tmp_path / "ok.png", "--scan", tmp_path / "none.npy"), "no such scan")):
        code, _, e = run_cli("run", out, *args, "--deadline", "5ms")
        assert code == 2 and msg in e and len(e.strip().splitlines()) == 1
    code, _, e = run_cli("run", tmp_path, "--image", tmp_path / "ok.png", "--scan", tmp_path / "scan.npy",
                         "--deadline", "5ms")
    assert code == 2 and "manifest.json" in e
    broken = tmp_path / "broken"
    broken.mkdir()
    manifest = json.loads((out / "manifest.json").read_text())
    (broken / "manifest.json").write_text(json.dumps(manifest))
    code, _, e = run_cli("run", broken, "--image", tmp_path / "ok.png", "--scan", tmp_path / "scan.npy",
                         "--deadline", "5ms")
    assert code == 2 and "missing" in e


def test_measured_curve_next_to_prediction(exported):
    from explorer.report import _measured_curve
    from explorer.calibration.curve import curve_check
    from conftest import TINY_DATA
    out, _ = exported
    res = curve_check(out, TINY_DATA, device="tx2-cpu", frames=2, deadlines=4)
    assert len(res["measured"]["loss"]) == 4 and len(res["path_losses"]) == CAND.num_paths
    assert res["measured_anytime_loss"] > 0 and res["predicted_anytime_loss"] > 0
    assert (out / "anytime_curve.json").is_file()
    assert _measured_curve(out / "anytime_curve.json")


@pytest.fixture(scope="module")
def int8_export(tmp_path_factory):
    from explorer.deploy.export import Quantization
    from conftest import TINY_DATA
    out = tmp_path_factory.mktemp("int8")
    torch.manual_seed(0)
    net = build_network(CAND)
    m = export_network(net, out / "m", (32, 48), quantization=Quantization(
        data=TINY_DATA, calibration_frames=4, eval_frames=6, max_degradation=10.0, stages="all"))
    return out / "m", m


def test_int8_export_records_every_path_before_and_after(int8_export):
    import onnx
    from conftest import TINY_DATA
    from explorer.deploy.quantize import _frames, path_metrics
    out, m = int8_export
    assert m.precision == "int8" and json.loads((out / "manifest.json").read_text()) == m.to_json()
    # the profiles priced the network searched in fp32: its manifest says its costs are fp32 estimates
    assert m.expected_cost_precision == "fp32" and m.expected_cost_note.startswith("fp32 estimates")
    # --int8-stages all: every stage graph but path 0's (the scan: nothing to quantize)
    assert [s.precision for s in m.stages] == ["fp32"] + ["int8"] * (len(m.stages) - 1)
    assert all(s.file.endswith(".int8.onnx") and (out / s.file).is_file() for s in m.stages[1:])
    assert sorted(f.name for f in out.glob("*.onnx")) == sorted(s.file for s in m.stages)   # no fp32 one left
    ops = {n.op_type for s in m.stages[1:] for n in onnx.load(str(out / s.file)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    q = m.quantization
    assert q.calibration.frames == 4 and q.evaluation.frames == 6
    assert len(m.path_metrics_fp32) == len(m.path_metrics_int8) == len(q.rmse_degradation) == CAND.num_paths
    assert m.path_metrics == m.path_metrics_int8
    # what the manifest says is what the int8 graphs give, and path 0 (no weights) is untouched
    again = path_metrics(out, _frames(TINY_DATA, (32, 48), 6, "val"))
    assert [p["rmse"] for p in again] == pytest.approx([p["rmse"] for p in m.path_metrics_int8], rel=1e-5)
    assert q.rmse_degradation[0] == 0.0
    for before, after, d in zip(m.path_metrics_fp32, m.path_metrics_int8, q.rmse_degradation):
        assert d == pytest.approx(after["rmse"] / before["rmse"] - 1) and d <= q.max_degradation


def test_int8_runs_under_deadlines(int8_export, run_cli):
    from conftest import TINY_DATA
    out, _ = int8_export
    runner = AnytimeRunner(out)
    img, scan = np.zeros((3, 32, 48), np.float32), np.ones(48, np.float32)
    assert runner.run(img, scan, deadline_ms=0).path == 0
    full = runner.run(img, scan, deadline_ms=10_000)
    errors = [m["rmse"] for m in runner.manifest.path_metrics]
    # every path ran; the one returned is the most accurate of them as the export measured it
    assert [p for p, _ in full.completed] == list(range(CAND.num_paths))
    assert full.path == int(np.argmin(errors))
    code, text, err = run_cli("curve", out, "--data", TINY_DATA, "--device", "tx2-cpu", "--frames", "2",
                              "--deadlines", "3")
    assert code == 0, err
    assert "the model is int8" in text and json.loads((out / "anytime_curve.json").read_text())["precision"] == "int8"
    assert "on 2 validation frames of" in " ".join(text.split())


def _calibrating_here(monkeypatch, tmp_path, asked: list) -> None:
    """``explorer curve``'s calibration stood in for by tx2-cpu's figures under this machine's identity
    (each call's options appended to ``asked``), and a cache folder of the test's own."""
    import dataclasses

    from explorer.calibration import curve, kept
    from explorer.cost import get_device
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path / "cache"))

    def calibrate(**kw):
        asked.append(kw)
        here = kept.this_machine(kw["provider"])
        profile = get_device("tx2-cpu")
        conditions = {field: here[key] for key, field in kept.IN_CONDITIONS.items()}
        return dataclasses.replace(profile, name="host", provenance={**profile.provenance, "conditions": conditions})
    monkeypatch.setattr(curve, "calibrate", calibrate)


def test_curve_without_a_profile_says_it_calibrates_first(exported, run_cli, monkeypatch, tmp_path):
    """No --device: the machine is calibrated before any deadline runs, which the user is told at once,
    with the ways to skip it; --quick asks for the short calibration."""
    from conftest import TINY_DATA
    asked = []
    _calibrating_here(monkeypatch, tmp_path, asked)
    out, _ = exported
    code, _, err = run_cli("curve", out, "--data", TINY_DATA, "--frames", "1", "--deadlines", "2", "--quick")
    assert code == 0, err
    assert "calibrated first" in err and "--device mybox.yaml" in err
    assert asked and asked[0]["scale"] == 0.35


def test_curve_keeps_its_calibration_for_the_next_call_on_this_machine(exported, run_cli, monkeypatch, tmp_path):
    """The profile a curve calibrates is kept (the path said) and the next curve on this machine uses it
    without calibrating; --recalibrate measures again; a quick one does not serve a full calibration,
    a full one serves --quick; another machine's identity finds none; --device skips it all."""
    import json

    from conftest import TINY_DATA
    from explorer.calibration import kept
    from explorer.cost import get_device
    asked = []
    _calibrating_here(monkeypatch, tmp_path, asked)
    out, _ = exported
    curve = ("curve", out, "--data", TINY_DATA, "--frames", "1", "--deadlines", "2")
    code, _, err = run_cli(*curve, "--quick")
    assert code == 0 and len(asked) == 1, err
    quick = kept.kept_path(kept.this_machine("CPUExecutionProvider"), quick=True)
    assert quick.is_file() and str(tmp_path / "cache") in str(quick)
    assert f"kept this machine's profile at {quick}" in " ".join(err.split())
    assert get_device(quick).name == "host"   # a profile file --device reads
    code, text, err = run_cli(*curve, "--quick", "--json")
    assert code == 0 and len(asked) == 1, err                       # reused: not calibrated again
    assert str(quick) in " ".join(err.split()) and "calibrated first" not in err
    assert json.loads(text)["device"] == "host"
    code, _, err = run_cli(*curve, "--quick", "--recalibrate")
    assert code == 0 and len(asked) == 2, err
    code, _, err = run_cli(*curve)                                  # a full calibration: the quick one won't do
    assert code == 0 and len(asked) == 3 and asked[-1]["scale"] == 0.5, err
    full = kept.kept_path(kept.this_machine("CPUExecutionProvider"), quick=False)
    assert full.is_file()
    code, _, err = run_cli(*curve, "--quick")                       # ... and the full one serves --quick
    assert code == 0 and len(asked) == 3 and str(full) in " ".join(err.split()), err
    code, _, err = run_cli(*curve, "--device", "tx2-cpu")
    assert code == 0 and len(asked) == 3 and "kept" not in err, err
    code, _, err = run_cli(*curve, "--device", "tx2-cpu", "--recalibrate")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--recalibrate" in err, err
    # another machine (another processor): its own file, none there yet, so it calibrates
    identity = kept.device_identity
    monkeypatch.setattr(kept, "device_identity", lambda *a: {**identity(*a), "cpu": "another processor"})
    code, _, err = run_cli(*curve, "--quick")
    assert code == 0 and len(asked) == 4 and "calibrated first" in err, err


def test_a_kept_profile_of_another_machine_or_damaged_serves_nothing(monkeypatch, tmp_path):
    """A kept file at this machine's place that records another processor, or that cannot be read,
    is not used (the calibration then made replaces it)."""
    import dataclasses

    from explorer.calibration import kept
    from explorer.cost import get_device
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path))
    here = kept.this_machine("CPUExecutionProvider")
    profile = get_device("tx2-cpu")
    conditions = {field: here[key] for key, field in kept.IN_CONDITIONS.items()}
    path = kept.keep_profile(dataclasses.replace(profile, provenance={**profile.provenance, "conditions": conditions}),
                             "CPUExecutionProvider", quick=False)
    assert kept.find_kept("CPUExecutionProvider", quick=False) == path
    assert kept.find_kept("CPUExecutionProvider", quick=True) == path
    kept.keep_profile(dataclasses.replace(profile, provenance={**profile.provenance, "conditions": {
        **conditions, "processor": "another processor"}}), "CPUExecutionProvider", quick=False)
    assert kept.find_kept("CPUExecutionProvider", quick=False) is None
    path.write_text("name: [unclosed")
    assert kept.find_kept("CPUExecutionProvider", quick=True) is None


def test_int8_stages_hand_each_other_uint8(int8_export):
    """The export quantizes a tensor two int8 stages pass with one scale on both sides (``share_edge_scales``),
    so the runner hands it over uint8 and the maps are those of the float handoff."""
    out, _ = int8_export
    runner, plain = AnytimeRunner(out), AnytimeRunner(out, handoff=False)
    assert plain.handed_off == {}
    assert "x0" in runner.handed_off and all(form.startswith("uint8") for form in runner.handed_off.values())
    handed = {n for _, _, ins, _ in runner.sessions for n in ins} - {"image", "scan"}
    assert handed and all(".uint8" in n for n in handed)   # every tensor between the int8 stages
    rng = np.random.default_rng(0)
    img, scan = rng.random((3, 32, 48), dtype=np.float32), rng.uniform(0.5, 8.0, 48).astype(np.float32)
    for a, b in zip(runner.depths(img, scan), plain.depths(img, scan)):
        np.testing.assert_array_equal(a, b)


def _stage_speeds(int8_ratio: dict[int, float], timed: list | None = None) -> "Callable":
    """A stand-in for quantize.compare_speed: every stage 2 ms in fp32, ``int8_ratio`` of that in int8
    (0.5 where not given); ``timed`` collects the stages of every configuration timed."""
    def speeds(model_dir, manifest, configs, frame):
        out = []
        for chosen in configs:
            if timed is not None:
                timed.append(sorted(chosen))
            per_stage = {k: 2.0 * (int8_ratio.get(k, 0.5) if k in chosen else 1.0)
                         for k in range(len(manifest.stages))}
            out.append((sum(per_stage.values()), per_stage))
        return out
    return speeds


def _metrics_losing(loss: float, spoils) -> "Callable":
    """A stand-in for quantize.path_metrics: every path's RMSE 1.0, and ``1 + loss`` from the first path
    after an int8 stage graph for which ``spoils(stage)`` holds (what the export's manifest says now)."""
    def metrics(model_dir, frames):
        stages = json.loads((model_dir / "manifest.json").read_text())["stages"]
        spoiled = [st["path"] for st in stages if st.get("precision") == "int8" and spoils(st)]
        return [{"path": p, "rmse": 1.0 + (loss if spoiled and p >= min(spoiled) else 0.0)}
                for p in range(CAND.num_paths)]
    return metrics


def test_int8_keeps_fp32_the_graph_that_costs_accuracy(exported, tmp_path, monkeypatch):
    """--int8-stages faster: a graph whose int8 form takes a path past --max-degradation goes back to
    fp32, the others stay int8, and the manifest says which and why."""
    import explorer.deploy.quantize as quantize
    from conftest import TINY_DATA
    from explorer.deploy.export import Quantization
    _, net = exported
    monkeypatch.setattr(quantize, "compare_speed", _stage_speeds({}))
    monkeypatch.setattr(quantize, "path_metrics", _metrics_losing(0.10, lambda st: st["path"] == 2))
    m = export_network(net, tmp_path / "m", (32, 48), quantization=Quantization(
        data=TINY_DATA, calibration_frames=2, eval_frames=2, max_degradation=0.03))
    precisions = [st.precision for st in m.stages]
    assert precisions == ["fp32", "int8", "fp32"] + ["int8"] * (len(m.stages) - 3)
    assert m.quantization.kept_fp32_for_accuracy == [m.stages[2].name]
    assert max(m.quantization.rmse_degradation) == 0.0
    assert sorted(f.name for f in (tmp_path / "m").glob("*.onnx")) == sorted(st.file for st in m.stages)
    assert json.loads((tmp_path / "m" / "manifest.json").read_text()) == m.to_json()


def test_int8_past_the_degradation_limit_is_refused_and_changes_nothing(exported, tmp_path, monkeypatch):
    import shutil
    import explorer.deploy.quantize as quantize
    from conftest import TINY_DATA
    from explorer.deploy.export import Quantization
    from explorer.errors import UserError
    out, net = exported
    target = tmp_path / "kept"
    shutil.copytree(out, target)
    before = {f.name: f.read_bytes() for f in target.iterdir()}
    monkeypatch.setattr(quantize, "compare_speed", _stage_speeds({}))   # every graph pays
    monkeypatch.setattr(quantize, "path_metrics", _metrics_losing(0.10, lambda stage: True))
    with pytest.raises(UserError, match=r"path \d's RMSE by 10\.0% even with only \S+ int8 .*--force"):
        export_network(net, target, (32, 48), quantization=Quantization(data=TINY_DATA, calibration_frames=2,
                                                                         eval_frames=2, max_degradation=0.03))
    assert {f.name: f.read_bytes() for f in target.iterdir()} == before      # the fp32 export is intact
    assert [p.name for p in tmp_path.iterdir()] == ["kept"]                 # no scratch folder left


def test_int8_keeps_a_stage_fp32_where_int8_is_not_faster_here(exported, tmp_path, monkeypatch):
    import explorer.deploy.quantize as quantize
    from conftest import TINY_DATA
    from explorer.deploy.export import Quantization
    _, net = exported
    timed = []
    # stage 1 twice as fast in int8, the others 0.97x their fp32 time: less than the 5% asked
    monkeypatch.setattr(quantize, "compare_speed", _stage_speeds({k: 0.97 for k in range(2, 9)}, timed))
    m = export_network(net, tmp_path / "m", (32, 48), quantization=Quantization(
        data=TINY_DATA, calibration_frames=2, eval_frames=2, max_degradation=10.0))
    quantized = list(range(1, len(m.stages)))   # every stage graph but path 0's
    # from all int8, each stage timed in the staged runtime int8 and fp32, the others as decided so far
    assert timed[:2] == [quantized, quantized[1:]] and timed[2:4] == [quantized, [1] + quantized[2:]]
    assert len(timed) == 2 * len(quantized)
    assert [s.precision for s in m.stages] == ["fp32", "int8"] + ["fp32"] * (len(m.stages) - 2)
    assert (m.stages[1].ms_here.fp32, m.stages[1].ms_here.int8) == (2.0, 1.0)
    assert m.stages[2].ms_here.int8 == pytest.approx(1.94)
    assert sorted(f.name for f in (tmp_path / "m").glob("*.onnx")) == sorted(s.file for s in m.stages)
    assert m.quantization.quantized_graphs == [m.stages[1].file.replace(".int8", "")]
    runner = AnytimeRunner(tmp_path / "m")   # fp32 and int8 stage graphs run together
    res = runner.run(np.zeros((3, 32, 48), np.float32), np.ones(48, np.float32))
    assert [p for p, _ in res.completed] == list(range(CAND.num_paths))


def test_int8_cli_options(run_cli, tmp_path):
    code, _, err = run_cli("export", "--checkpoint", "x.pt", "--out", tmp_path / "o", "--quantize", "int4")
    assert code == 2 and "--quantize int4" in err
    code, _, err = run_cli("export", "--checkpoint", "x.pt", "--out", tmp_path / "o", "--force")
    assert code == 2 and "--quantize int8 only" in err
    code, _, err = run_cli("export", "--checkpoint", "x.pt", "--out", tmp_path / "o", "--quantize", "int8",
                           "--max-degradation", "lots")
    assert code == 2 and "not a percentage" in err
    code, _, err = run_cli("export", "--checkpoint", "x.pt", "--out", tmp_path / "o", "--int8-stages", "all")
    assert code == 2 and "--quantize int8 only" in err
    code, _, err = run_cli("export", "--checkpoint", "x.pt", "--out", tmp_path / "o", "--quantize", "int8",
                           "--int8-stages", "some")
    assert code == 2 and "--int8-stages" in err and len(err.strip().splitlines()) == 1
