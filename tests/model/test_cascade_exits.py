"""Exits that build on each other (``Candidate.exit_cascade``): the first exit corrects the scan, each
later one the exit before it, through the one model definition (forward pass, costs, the shipped
network)."""

import dataclasses

import pytest
import torch

from explorer.cost import candidate_cost, available_devices, get_device
from explorer.model import build_network, stage_specs
from explorer.model.shipped import ship
from explorer.space import Candidate

#: every kind of exit (the LiDAR-only one, fused encoder exits, the ECU's, decoder exits), in a cascade
CASCADE = Candidate(encoder_blocks=6, width_mult=0.25, lidar_depth=4, lidar_width=8, ecu_band=1, ecu_width=16,
                    decoder_widths=(32, 16, 16, 8), exits=(0, 1, 2, 4), head_depth=2, head_width=8,
                    encoder_exits=(3, 5), lidar_exit=True, lidar_first=True, exit_residual=True, exit_cascade=True)
RESIDUAL = dataclasses.replace(CASCADE, exit_cascade=False)


def _randomised(candidate: Candidate) -> torch.nn.Module:
    torch.manual_seed(0)
    net = build_network(candidate).eval()
    for p in net.parameters():   # corrections unlike zero, so that what each exit adds to shows
        p.data.normal_(0, 0.1)
    return net


def test_the_first_exit_corrects_the_scan_and_each_later_one_the_exit_before():
    exits = [s for s in stage_specs(CASCADE) if s.path is not None]
    assert exits[0].name == "lidar_exit" and exits[0].inputs[-1] == "scan_fill"
    assert [s.inputs[-1] for s in exits[1:]] == [f"depth_{s.path - 1}" for s in exits[1:]]
    assert all(s.config.cascade for s in exits[1:])
    # without the LiDAR-only exit the first image exit corrects the scan, and is no cascade head
    first = next(s for s in stage_specs(dataclasses.replace(CASCADE, lidar_exit=False)) if s.path is not None)
    assert first.inputs[-1] == "scan_fill" and not first.config.cascade


@pytest.mark.parametrize("lidar_exit", [True, False])
def test_each_path_is_the_previous_path_plus_its_heads_correction(lidar_exit):
    cand = dataclasses.replace(CASCADE, lidar_exit=lidar_exit)
    net = _randomised(cand)
    image, scan = torch.rand(2, 3, 32, 48), torch.rand(2, 48) * 4 + 0.5
    env = {"image": image, "scan": scan}
    with torch.no_grad():
        depths = net(image, scan)
        for spec in net.specs:
            net.run_stage(spec, env, 16)
        for spec in (s for s in net.specs if s.path is not None):
            before = env[spec.inputs[-1]]
            module = net.stages[spec.name]
            args = [env[n] for n in spec.inputs[:-1]] + [torch.zeros_like(before)]
            correction = module(*args)
            expected = depths[spec.path - 1] if spec.path > 1 else depths[0]   # path 0 is the scan fill
            assert torch.allclose(before, expected)
            assert torch.allclose(depths[spec.path], before + correction, atol=1e-6)
            assert correction.abs().max() > 0
    assert len(depths) == cand.num_paths


def test_a_cascade_costs_what_residual_exits_cost_on_every_device_its_adds_included():
    cascade, residual = candidate_cost(CASCADE, (64, 64)), candidate_cost(RESIDUAL, (64, 64))
    adds = [w for w in cascade.workloads if w.layer == "correct"]   # each exit's add to the map it corrects
    assert {w.stage for w in adds} == {s.name for s in stage_specs(CASCADE) if s.path is not None}
    assert all(w.kind == "add" and w.out_shape == (1, 64, 64) and w.bytes_read for w in adds)   # full size
    for name in available_devices():
        device = get_device(name)
        if CASCADE.precision not in device.precisions:
            continue
        assert cascade.path_latency_ms(device) == residual.path_latency_ms(device)
        without_adds = [w for w in cascade.workloads if w not in adds]
        assert sum(device.layer_ms(w) for w in adds) > 0
        assert sum(device.layer_ms(w) for w in without_adds) < sum(device.layer_ms(w) for w in cascade.workloads)


def test_an_exit_a_later_exit_corrects_is_shipped_whatever_its_error():
    #          scan  lidar  b3    b5    ECU   1     2     4
    losses = [0.90, 0.70, 0.75, 0.60, 0.60, 0.50, 0.55, 0.58]
    assert ship(CASCADE, losses).candidate == CASCADE and ship(CASCADE, losses).dropped == ()
    # the same losses drop three exits of the residual network, whose exits all correct the scan
    assert [d.exit for d in ship(RESIDUAL, losses).dropped] == ["exit_b3", "exit_0", "exit_2"]


def test_a_cascade_needs_residual_exits():
    assert not Candidate(exit_cascade=True).exit_cascade    # canonical: no residual exits, no cascade
    assert Candidate(exit_cascade=True).key == Candidate().key
    assert "exit_cascade" not in RESIDUAL.to_dict() and CASCADE.to_dict()["exit_cascade"] is True
    assert "the exit before it" in CASCADE.describe()
