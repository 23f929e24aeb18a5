import json
import threading

import numpy as np
import pytest
import torch

from explorer.deploy import export_from_checkpoint, export_network
from explorer.model import build_network
from explorer.runtime import AnytimeRunner
from explorer.space import SearchSpace, paper_candidate
from explorer.train import TrainConfig, save_checkpoint

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
    assert m["verification"]["max_abs_diff"] <= 1e-4
    # path 0, then one graph per exit: encoders+ECU+exit, decoder 1+exit, decoder 2+exit, decoders 3-4+exit
    assert [s["path"] for s in m["stages"]] == [0, 1, 2, 3, 4]
    assert m["stages"][4]["stages"] == ["decoder_3", "decoder_4", "exit_4"]


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


def test_export_from_checkpoint(tmp_path):
    net = build_network(CAND)
    save_checkpoint(tmp_path / "c.pt", net, TrainConfig(input_size=(32, 32)), 1)
    m = export_from_checkpoint(tmp_path / "c.pt", tmp_path / "out")
    assert m["input_size"] == [32, 32] and (tmp_path / "out" / m["stages"][1]["file"]).is_file()


def test_run_cli_and_bad_inputs(exported, tmp_path, run_cli):
    from PIL import Image
    out, _ = exported
    Image.fromarray(np.zeros((32, 48, 3), np.uint8)).save(tmp_path / "ok.png")
    Image.fromarray(np.zeros((40, 48, 3), np.uint8)).save(tmp_path / "big.png")
    np.save(tmp_path / "scan.npy", np.full(48, 2.0, np.float32))
    (tmp_path / "short.csv").write_text(",".join(["2.0"] * 40))
    code, o, e = run_cli("run", out, "--image", tmp_path / "ok.png", "--scan", tmp_path / "scan.npy",
                         "--deadline", "0ms", "--out", tmp_path / "d.png", "--json")
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
    from explorer.runtime import curve_check
    from conftest import TINY_DATA
    out, _ = exported
    res = curve_check(out, TINY_DATA, device="tx2-cpu", frames=2, deadlines=4)
    assert len(res["measured"]["loss"]) == 4 and len(res["path_losses"]) == CAND.num_paths
    assert res["measured_anytime_loss"] > 0 and res["predicted_anytime_loss"] > 0
    assert (out / "anytime_curve.json").is_file()
    assert _measured_curve(out / "anytime_curve.json")
