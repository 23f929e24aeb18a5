"""A real LiDAR's ranges by angle, projected into the image by the runtime (``explorer run --lidar``)."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from explorer.deploy.export import export_network
from explorer.deploy.runtime import AnytimeRunner, scale_intrinsics
from explorer.errors import UserError
from explorer.model import build_network
from explorer.scan import read_lidar_yaml
from explorer.space import SearchSpace

SIZE = (32, 48)                    # the model's input; its scan row is 16
IMAGE = (64, 96)                   # the camera's frames, twice that
K_IMAGE = np.array([[80.0, 0, 47.5], [0, 80.0, 32.5], [0, 0, 1]])   # at the input size: f 40, centre (23.5, 16)
LEVEL = "fov: 180\nresolution: 0.25\nrange_min: 0.05\nrange_max: 10\n"
WALL = 3.0                         # metres ahead of the camera, facing it


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    out = tmp_path_factory.mktemp("model")
    torch.manual_seed(0)
    export_network(build_network(list(SearchSpace.from_yaml("tiny").enumerate())[-1]), out, SIZE, devices=())
    return out


def _wall_ranges(lidar) -> np.ndarray:
    """Each beam's exact range to the plane z = WALL of the camera's frame (inf: it never meets it or
    meets it out of range)."""
    T = lidar.transform
    a = lidar.angle_min + lidar.angle_increment * np.arange(lidar.beams)
    d = T[:3, :3] @ np.stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    with np.errstate(divide="ignore"):
        r = (WALL - T[2, 3]) / d[2]
    return np.where((d[2] > 1e-9) & (r <= lidar.range_max), r, np.inf)


def _files(tmp_path, mount=""):
    from PIL import Image
    (tmp_path / "lidar.yaml").write_text(LEVEL + mount)
    lidar = read_lidar_yaml(tmp_path / "lidar.yaml")
    np.savetxt(tmp_path / "ranges.csv", _wall_ranges(lidar)[None], delimiter=",")
    (tmp_path / "intrinsics.txt").write_text("80 80 47.5 32.5\n")
    pixels = np.random.default_rng(0).integers(0, 256, (*IMAGE, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "frame.png")
    # what --lidar resizes it to, given without --lidar
    Image.fromarray(pixels).resize((SIZE[1], SIZE[0]), Image.Resampling.BILINEAR).save(tmp_path / "small.png")
    return lidar, pixels


def test_intrinsics_scale_as_pixel_index_coordinates():
    K = scale_intrinsics(K_IMAGE, IMAGE, SIZE)
    np.testing.assert_allclose(K, [[40, 0, 23.5], [0, 40, 16], [0, 0, 1]])
    u = 10.0   # a point at column 10 of the frame lies at (10 + 0.5) / 2 - 0.5 of the input
    x = (u - K_IMAGE[0, 2]) / K_IMAGE[0, 0]
    assert K[0, 0] * x + K[0, 2] == pytest.approx((u + 0.5) / 2 - 0.5)


def test_a_level_lidar_at_the_optical_centre_gives_the_wall_on_the_scan_row(model, tmp_path, capsys):
    lidar, pixels = _files(tmp_path)
    runner = AnytimeRunner(model)
    scan = runner.scan_from_ranges(_wall_ranges(lidar), lidar, K_IMAGE, IMAGE)
    assert scan.shape == (SIZE[1],)
    np.testing.assert_allclose(scan, WALL, rtol=1e-5)   # every column has a return, at the wall's depth
    p = runner.last_scan
    assert p.row == runner.scan_row == 16 and (p.rows == 16).all() and p.columns == SIZE[1]
    assert capsys.readouterr().err == ""   # on the model's row: nothing to say
    from explorer.deploy.runtime import fit_image
    img = fit_image(pixels, SIZE)
    np.testing.assert_array_equal(runner.run(img, scan).depth, runner.run(img, np.full(SIZE[1], WALL)).depth)


def test_run_with_lidar_matches_run_with_its_per_column_scan(model, tmp_path, run_cli):
    _files(tmp_path)
    np.save(tmp_path / "columns.npy", np.full(SIZE[1], WALL, np.float32))
    code, out, err = run_cli("run", model, "--image", tmp_path / "frame.png", "--scan", tmp_path / "ranges.csv",
                             "--lidar", tmp_path / "lidar.yaml", "--intrinsics", tmp_path / "intrinsics.txt",
                             "--deadline", "10s", "--out", tmp_path / "lidar.npy", "--json")
    assert code == 0 and err == ""
    res = json.loads(out)
    assert res["scan_row"] == 16 and res["scan_rows"] == [16, 16] and res["projected_row"] == 16
    assert res["scan_columns"] == SIZE[1]
    code, out, _ = run_cli("run", model, "--image", tmp_path / "small.png", "--scan", tmp_path / "columns.npy",
                           "--deadline", "10s", "--out", tmp_path / "columns_out.npy", "--json")
    assert code == 0 and "scan_rows" not in json.loads(out)   # without --lidar: as before
    assert res["path"] == json.loads(out)["path"]
    np.testing.assert_allclose(np.load(tmp_path / "lidar.npy"), np.load(tmp_path / "columns_out.npy"),
                               rtol=1e-5, atol=1e-5)


def test_a_tilted_mount_is_warned_about_once(model, tmp_path, run_cli, capsys):
    lidar, _ = _files(tmp_path, "tilt: 10\n")   # tan 10° x f 40: about 7 rows below the scan row
    runner = AnytimeRunner(model)
    capsys.readouterr()
    for _ in range(2):
        runner.scan_from_ranges(_wall_ranges(lidar), lidar, K_IMAGE, IMAGE)
    assert runner.last_scan.row == 23
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "row 23" in err[0] and "row 16" in err[0]
    assert "retrain with this LiDAR's mount (--lidar)" in err[0]
    code, out, err = run_cli("run", model, "--image", tmp_path / "frame.png", "--scan", tmp_path / "ranges.csv",
                             "--lidar", tmp_path / "lidar.yaml", "--intrinsics", tmp_path / "intrinsics.txt",
                             "--deadline", "10s", "--json")
    assert code == 0 and len(err.strip().splitlines()) == 1 and "warning" in err   # a warning, not an error
    assert json.loads(out)["projected_row"] == 23


def test_bad_lidar_inputs_are_one_line_errors(model, tmp_path, run_cli):
    lidar, _ = _files(tmp_path)
    (tmp_path / "short.csv").write_text(",".join(["3.0"] * (lidar.beams - 1)))
    (tmp_path / "skew.yaml").write_text(LEVEL + "T_cam_lidar: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n")
    (tmp_path / "behind.yaml").write_text(LEVEL + "yaw: 180\n")
    (tmp_path / "flat.txt").write_text("80 -80 47.5 32.5\n")
    f = {n: tmp_path / n for n in ("frame.png", "ranges.csv", "lidar.yaml", "intrinsics.txt")}
    base = ["--image", f["frame.png"], "--deadline", "5ms", "--out", tmp_path / "never.png"]
    cases = [
        (["--scan", tmp_path / "short.csv", "--lidar", f["lidar.yaml"], "--intrinsics", f["intrinsics.txt"]],
         f"{lidar.beams - 1} ranges"),
        (["--scan", f["ranges.csv"], "--lidar", tmp_path / "skew.yaml", "--intrinsics", f["intrinsics.txt"]],
         "not a rigid transform"),
        (["--scan", f["ranges.csv"], "--lidar", tmp_path / "behind.yaml", "--intrinsics", f["intrinsics.txt"]],
         "no return of this scan lands in the image"),
        (["--scan", f["ranges.csv"], "--lidar", f["lidar.yaml"], "--intrinsics", tmp_path / "flat.txt"],
         "focal lengths"),
        (["--scan", f["ranges.csv"], "--lidar", tmp_path / "none.yaml", "--intrinsics", f["intrinsics.txt"]],
         "no such file"),
        (["--scan", tmp_path / "none.csv", "--lidar", f["lidar.yaml"], "--intrinsics", f["intrinsics.txt"]],
         "no such scan file"),
        (["--scan", f["ranges.csv"], "--lidar", f["lidar.yaml"], "--intrinsics", tmp_path / "none.txt"],
         "no such intrinsics file"),
        (["--scan", f["ranges.csv"], "--lidar", f["lidar.yaml"]], "--lidar needs --intrinsics"),
        (["--scan", f["ranges.csv"], "--intrinsics", f["intrinsics.txt"]], "only with --lidar"),
    ]
    for args, msg in cases:
        code, _, err = run_cli("run", model, *base, *args)
        assert code == 2 and msg in err and len(err.strip().splitlines()) == 1, (msg, err)
    assert not (tmp_path / "never.png").exists()


def test_the_api_checks_its_inputs(model, tmp_path):
    lidar, _ = _files(tmp_path)
    runner = AnytimeRunner(model, warmup=False)
    ranges = _wall_ranges(lidar)
    with pytest.raises(UserError, match="ranges, the LiDAR's model has"):
        runner.scan_from_ranges(ranges[:-1], lidar, K_IMAGE, IMAGE)
    with pytest.raises(UserError, match="no return of this scan"):
        runner.scan_from_ranges(np.full_like(ranges, np.inf), lidar, K_IMAGE, IMAGE)
    with pytest.raises(UserError, match="3x3"):
        runner.scan_from_ranges(ranges, lidar, K_IMAGE[:2], IMAGE)


def test_the_runtime_imports_no_torch():
    code = "import sys, explorer.deploy.runtime; print('torch' in sys.modules, 'explorer.data' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


@pytest.fixture(scope="module")
def slanted_model(tmp_path_factory):
    """A model measured on frames whose scans are rolled across the image: its graphs take the rows."""
    from explorer.deploy.export import Measurement
    out = tmp_path_factory.mktemp("slanted")
    torch.manual_seed(0)
    net = build_network(list(SearchSpace.from_yaml("tiny").enumerate())[-1])
    export_network(net, out, SIZE, devices=(), measurement=Measurement("synthetic:48:16,roll=10", 4))
    return out, net


def test_a_network_measured_on_slanted_scans_takes_each_columns_row(slanted_model, tmp_path, capsys):
    from explorer.data import open_dataset
    out, net = slanted_model
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["scan_rows_input"] and any("scan_rows" in s["inputs"] for s in manifest["stages"])
    item = open_dataset("synthetic:48:16,roll=10", "val", SIZE, train_augment=False)[0]
    assert len(set(item["scan_rows"].tolist())) > 1
    runner = AnytimeRunner(out)
    got = runner.depths(item["image"].numpy(), item["scan"].numpy(), item["scan_rows"].numpy())
    with torch.no_grad():
        want = net.eval()(item["image"][None], item["scan"][None], item["scan_rows"][None])
    assert all(np.allclose(g, w[0, 0].numpy(), atol=1e-4) for g, w in zip(got, want))
    lidar, _ = _files(tmp_path, "roll: 10\ntilt: 10\n")
    capsys.readouterr()
    runner.scan_from_ranges(_wall_ranges(lidar), lidar, K_IMAGE, IMAGE)
    assert capsys.readouterr().err == ""          # the graphs read the scan on its own rows: nothing to warn of
    with pytest.raises(UserError, match="one image row"):
        runner.depths(item["image"].numpy(), item["scan"].numpy(), np.zeros(3))


def test_int8_of_a_network_on_slanted_scans_is_refused_in_one_line(tmp_path):
    from explorer.deploy.export import Measurement, Quantization
    with pytest.raises(UserError, match="not supported yet"):
        export_network(build_network(list(SearchSpace.from_yaml("tiny").enumerate())[-1]), tmp_path / "q", SIZE,
                       devices=(), measurement=Measurement("synthetic:48:16,roll=10", 4), quantization=Quantization())
    assert not (tmp_path / "q").exists()
