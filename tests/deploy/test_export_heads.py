"""A network whose encoder and ECU exits have heads sized for their position, exported in fp32 (verified
against PyTorch, run by the anytime runtime) and in int8."""

import dataclasses

import numpy as np
import torch

from explorer.deploy.export import export_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.model import build_network
from explorer.space import Candidate

SIZED = Candidate(encoder_blocks=3, width_mult=0.25, lidar_depth=2, lidar_width=8, ecu_band=1, ecu_width=16,
                  decoder_widths=(16, 8), exits=(0, 1, 2), head_depth=1, encoder_exits=(2,),
                  encoder_head_depth=2, encoder_head_width=4, ecu_head_depth=2, ecu_head_width=16)
SIZE = (32, 48)


def _network(candidate=SIZED):
    torch.manual_seed(0)
    net = build_network(candidate).eval()
    for p in net.parameters():
        p.data.normal_(0, 0.1)
    return net


def _inputs():
    image = np.random.default_rng(0).random((3, *SIZE), dtype=np.float32)
    scan = np.linspace(1, 4, SIZE[1], dtype=np.float32)
    return image, scan


def test_fp32_export_verifies_and_the_runtime_runs_every_path(tmp_path):
    net = _network()
    manifest = export_network(net, tmp_path / "m", SIZE, devices=("tx2",))
    assert manifest.verification.max_abs_diff <= 1e-4
    image, scan = _inputs()
    with torch.no_grad():
        ref = net(torch.from_numpy(image)[None], torch.from_numpy(scan)[None])
    every = AnytimeRunner(tmp_path / "m").depths(image, scan)
    assert len(every) == SIZED.num_paths
    assert all(np.abs(d - r[0, 0].numpy()).max() <= 1e-4 for d, r in zip(every, ref))


def test_int8_export_runs(tmp_path):
    from conftest import TINY_DATA
    from explorer.deploy.export import Quantization
    cand = dataclasses.replace(SIZED, exit_residual=True)
    m = export_network(_network(cand), tmp_path / "m", SIZE, devices=(), quantization=Quantization(
        data=TINY_DATA, calibration_frames=4, eval_frames=4, max_degradation=10.0, stages="all"))
    assert m.precision == "int8" and len(m.path_metrics_int8) == cand.num_paths
    res = AnytimeRunner(tmp_path / "m").run(*_inputs())
    assert [p for p, _ in res.completed] == list(range(cand.num_paths))
