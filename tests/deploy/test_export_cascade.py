"""A cascade (each exit correcting the one before it) exported as stage graphs that hand the previous
exit's depth map on, in fp32 and int8, and run by the anytime runtime."""

import numpy as np
import pytest
import torch

from explorer.deploy.export import export_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.model import build_network
from explorer.space import Candidate

#: the LiDAR-only exit, an encoder exit, the ECU's and both decoder exits, in a cascade (stride 4)
CASCADE = Candidate(encoder_blocks=3, width_mult=0.25, lidar_depth=2, lidar_width=8, ecu_band=1, ecu_width=16,
                    decoder_widths=(16, 8), exits=(0, 1, 2), head_depth=1, encoder_exits=(2,), lidar_exit=True,
                    exit_residual=True, exit_cascade=True)
SIZE = (32, 48)


def _network():
    torch.manual_seed(0)
    net = build_network(CASCADE).eval()
    for p in net.parameters():   # corrections unlike zero, so that a map handed on wrong shows
        p.data.normal_(0, 0.1)
    return net


def _inputs():
    image = np.random.default_rng(0).random((3, *SIZE), dtype=np.float32)
    scan = np.linspace(1, 4, SIZE[1], dtype=np.float32)
    scan[5:9] = 0.0
    return image, scan


@pytest.fixture(scope="module")
def fp32_export(tmp_path_factory):
    out = tmp_path_factory.mktemp("cascade") / "m"
    net = _network()
    return out, net, export_network(net, out, SIZE, devices=("tx2",))


def test_each_stage_graph_reads_the_previous_exits_depth_map(fp32_export):
    _, _, manifest = fp32_export
    assert manifest.verification.max_abs_diff <= 1e-4      # every path as PyTorch computes it
    graphs = [s for s in manifest.stages if s.path and s.path > 1]
    assert graphs and all(f"depth_{s.path - 1}" in s.inputs for s in graphs)
    # the scan's fill is read by the first exit alone: it is not handed on to later graphs
    first = next(s for s in manifest.stages if s.path == 1)
    assert first.stages == ["scan_fill", "lidar_exit"] and "scan_fill" not in first.outputs
    assert not any("scan_fill" in s.inputs for s in manifest.stages)


def test_the_runtime_runs_a_cascade_path_by_path(fp32_export):
    out, net, _ = fp32_export
    image, scan = _inputs()
    with torch.no_grad():
        ref = net(torch.from_numpy(image)[None], torch.from_numpy(scan)[None])
    runner = AnytimeRunner(out)
    full = runner.run(image, scan)
    assert [p for p, _ in full.completed] == list(range(CASCADE.num_paths))
    assert full.path == CASCADE.num_paths - 1
    assert np.abs(full.depth - ref[-1][0, 0].numpy()).max() <= 1e-4
    every = runner.depths(image, scan)
    assert all(np.abs(d - r[0, 0].numpy()).max() <= 1e-4 for d, r in zip(every, ref))


def test_a_cascade_exports_in_int8_and_runs(tmp_path):
    import onnx
    from conftest import TINY_DATA
    from explorer.deploy.int8_graphs import uint8_edges
    from explorer.deploy.export import Quantization
    m = export_network(_network(), tmp_path / "m", SIZE, devices=(), quantization=Quantization(
        data=TINY_DATA, calibration_frames=4, eval_frames=4, max_degradation=10.0, stages="all"))
    assert m.precision == "int8" and [s.precision for s in m.stages] == ["fp32"] + ["int8"] * (len(m.stages) - 1)
    assert len(m.path_metrics_int8) == CASCADE.num_paths
    image, scan = _inputs()
    runner = AnytimeRunner(tmp_path / "m")
    res = runner.run(image, scan)
    assert [p for p, _ in res.completed] == list(range(CASCADE.num_paths))
    # features pass between the int8 graphs as uint8; each depth map stays float, read by the next exit
    assert runner.handed_off and not any(n.startswith("depth_") for n in runner.handed_off)
    with torch.no_grad():
        ref = _network()(torch.from_numpy(image)[None], torch.from_numpy(scan)[None])
    depths = runner.depths(image, scan)
    assert all(d.dtype == np.float32 and np.abs(d - r[0, 0].numpy()).max() < 0.2 for d, r in zip(depths, ref))
    # and so as the calibration bundle times int8 graphs
    models = [onnx.load(str(tmp_path / "m" / s.file)) for s in m.stages[1:]]
    handed = uint8_edges(models)
    assert handed and not any(n.startswith("depth_") for n in handed)
