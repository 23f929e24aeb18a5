"""An export carries the validation frames ``explorer curve`` measures on (``curve_frames.npz``, named
and hashed in the manifest), and the curve predicts a device the manifest prices from its expected
costs: neither needs torch, so the runtime install measures a curve too."""

import json
import shutil

import numpy as np
import pytest
import torch

from conftest import TINY_DATA
from explorer.calibration import curve as curve_module
from explorer.data import open_dataset
from explorer.deploy.curve import CURVE_FRAME_COUNT, device_curve, read_curve_frames, write_curve_frames
from explorer.deploy.export import Measurement, export_network
from explorer.deploy.manifest import CURVE_FRAMES, read_manifest
from explorer.errors import UserError
from explorer.model import build_network
from explorer.space import SearchSpace

CAND = list(SearchSpace.from_yaml("tiny").enumerate())[-1]
SIZE = (32, 48)


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    out = tmp_path_factory.mktemp("curve") / "model"
    torch.manual_seed(0)
    export_network(build_network(CAND), out, SIZE, devices=("tx2",), measurement=Measurement(TINY_DATA, 6))
    return out


def test_the_export_carries_the_first_validation_frames_of_its_data(measured):
    manifest = read_manifest(measured)
    entry = manifest.curve_frames
    assert entry.file == CURVE_FRAMES and entry.data == TINY_DATA and entry.split == "val"
    assert json.loads((measured / "manifest.json").read_text())["curve_frames"]["sha256"] == entry.sha256
    ds = open_dataset(TINY_DATA, "val", SIZE, train_augment=False)
    assert entry.frames == min(CURVE_FRAME_COUNT, len(ds))   # more than the 6 the paths were measured on
    stored = np.load(measured / CURVE_FRAMES)
    assert sorted(stored.files) == ["depth", "image", "scan"]   # no scan_rows: the graphs take none
    assert stored["image"].dtype == np.float32 and stored["image"].shape == (entry.frames, 3, *SIZE)
    for i in range(entry.frames):
        for key in ("image", "scan", "depth"):
            assert np.array_equal(stored[key][i], ds[i][key].numpy()), (i, key)


def test_frames_without_depth_are_not_stored(tmp_path):
    items = [{"image": np.zeros((3, *SIZE), np.float32), "scan": np.ones(SIZE[1], np.float32),
              "depth": np.zeros((1, *SIZE), np.float32)}] * 3
    assert write_curve_frames(tmp_path, items, "frames:x", rows_input=False) is None
    assert not (tmp_path / CURVE_FRAMES).exists()


def test_a_re_export_without_frames_leaves_none_behind(measured, tmp_path):
    out = tmp_path / "model"
    shutil.copytree(measured, out)
    export_network(build_network(CAND), out, SIZE, devices=())
    assert read_manifest(out).curve_frames is None and not (out / CURVE_FRAMES).exists()


def test_the_curve_of_a_priced_device_comes_from_the_manifest(measured, monkeypatch, run_cli):
    def no_pricing(*args, **kwargs):
        raise AssertionError("priced again: the manifest holds the device's costs")
    monkeypatch.setattr(curve_module, "candidate_cost", no_pricing)
    monkeypatch.setattr(curve_module, "open_dataset", no_pricing)   # nor read the data: the export has the frames
    expected = read_manifest(measured).expected_cost["tx2"].latency_ms
    code, out, err = run_cli("curve", measured, "--device", "tx2", "--frames", "40", "--deadlines", "3", "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["predicted_costs_ms"] == expected and res["device"] == "tx2" and res["predicted_from"] == "manifest"
    assert res["frames"] == CURVE_FRAME_COUNT and res["data"] == TINY_DATA and len(res["measured"]["loss"]) == 3
    assert "--frames 40: the export carries 16 validation frames" in err and err.count("\n") == 1
    # the torch-free curve, as the runtime install runs it, predicts the same
    again = device_curve(measured, "tx2", frames=2, deadlines=3)
    assert again["predicted_costs_ms"] == expected and again["frames"] == 2


def test_a_device_the_manifest_does_not_price_is_priced_with_its_profile(measured):
    res = curve_module.curve_check(measured, None, "tx2-cpu", frames=2, deadlines=3)
    assert res["predicted_from"] == "profile" and res["device"] == "tx2-cpu"


def test_tampered_frames_are_refused_in_one_line(measured, tmp_path, run_cli):
    out = tmp_path / "model"
    shutil.copytree(measured, out)
    with open(out / CURVE_FRAMES, "ab") as f:
        f.write(b"\0")
    code, _, err = run_cli("curve", out, "--device", "tx2", "--deadlines", "3")
    assert code == 2 and err.count("\n") == 1 and "do not match the manifest" in err and "Traceback" not in err
    with pytest.raises(UserError, match="do not match"):
        read_curve_frames(out, read_manifest(out), 4)


def test_the_runtime_install_says_what_it_cannot_do_in_one_line(measured, monkeypatch, run_cli):
    from explorer.cli import _common, deploy
    for module in (_common, deploy):   # as if torch and the search were not installed
        monkeypatch.setattr(module, "runtime_install", lambda: True)
    for args in ((), ("--device", "rpi4")):
        code, _, err = run_cli("curve", measured, *args)
        assert code == 2 and err.count("\n") == 1, err
        assert "this export prices tx2" in err and "probe bundle" in err and "--device mybox.yaml" in err
    code, _, err = run_cli("curve", measured, "--device", "tx2", "--data", "synthetic")
    assert code == 2 and err.count("\n") == 1 and "needs torch" in err and "runtime install" in err


def test_graphs_that_take_scan_rows_get_them_from_the_stored_frames(tmp_path):
    data = "synthetic:48:16,roll=10"   # scans rolled across the image: the graphs take each column's row
    torch.manual_seed(0)
    export_network(build_network(CAND), tmp_path / "m", SIZE, devices=("tx2",), measurement=Measurement(data, 4))
    stored = np.load(tmp_path / "m" / CURVE_FRAMES)
    rows = open_dataset(data, "val", SIZE, train_augment=False)[1]["scan_rows"].numpy()
    assert stored["scan_rows"].dtype == np.int64 and np.array_equal(stored["scan_rows"][1], rows)
    assert device_curve(tmp_path / "m", "tx2", frames=2, deadlines=2)["frames"] == 2
