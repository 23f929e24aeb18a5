"""Exit heads sized for their position: the encoder exits' and the ECU exit's heads are built, run and
costed at their own depth and width, the decoder exits' at ``head_depth``/``head_width``."""

import dataclasses

import torch

from explorer.cost import candidate_cost
from explorer.cost.devices import available_devices, get_device
from explorer.model import build_network, stage_specs
from explorer.space import Candidate

#: an encoder exit, the ECU's and both decoder exits (stride 4), one-layer heads but where sized
BASE = Candidate(encoder_blocks=3, width_mult=0.25, lidar_depth=2, lidar_width=8, ecu_band=1, ecu_width=16,
                 decoder_widths=(16, 8), exits=(0, 1, 2), head_depth=1, encoder_exits=(2,))
SIZED = dataclasses.replace(BASE, encoder_head_depth=2, encoder_head_width=4, ecu_head_depth=2, ecu_head_width=16)


def _heads(candidate):
    return {s.name: (s.config.depth, s.config.width) for s in stage_specs(candidate) if s.name.startswith("exit")}


def test_each_position_builds_its_own_head_and_the_network_runs():
    assert _heads(SIZED) == {"exit_b2": (2, 4), "exit_0": (2, 16), "exit_1": (1, 0), "exit_2": (1, 0)}
    net = build_network(SIZED).eval()
    assert net.stages["exit_0"].layers[0].out_channels == 16 and net.stages["exit_b2"].layers[0].out_channels == 4
    image, scan = torch.rand(2, 3, 32, 48), torch.rand(2, 48) * 4 + 0.5
    with torch.no_grad():
        paths = net(image, scan)
    assert len(paths) == SIZED.num_paths and all(p.shape == (2, 1, 32, 48) for p in paths)
    # the decoder exits keep head_depth: a network whose heads are all two layers differs there
    both = dataclasses.replace(SIZED, head_depth=2, head_width=8)
    assert _heads(both)["exit_1"] == (2, 8) and _heads(both)["exit_0"] == (2, 16)


def test_a_wider_ecu_head_costs_more_on_every_profile():
    narrow = dataclasses.replace(SIZED, ecu_head_width=4)
    wide, small = candidate_cost(SIZED, (32, 48)), candidate_cost(narrow, (32, 48))
    layers = lambda cost, stage: [w for w in cost.workloads if w.stage == stage]   # noqa: E731
    assert sum(w.macs for w in layers(wide, "exit_0")) > sum(w.macs for w in layers(small, "exit_0"))
    assert len(layers(wide, "exit_0")) > len(layers(candidate_cost(BASE, (32, 48)), "exit_0"))
    ecu_path = 2   # after path 0 (the scan) and path 1 (the encoder exit)
    assert [s.path for s in stage_specs(SIZED) if s.name == "exit_0"] == [ecu_path]
    for device in available_devices():
        profile = get_device(device)
        a, b = wide.path_latency_ms(profile), small.path_latency_ms(profile)
        assert a[ecu_path] > b[ecu_path] and a[1] == b[1], device   # the encoder exit's path is untouched
        e, f = wide.path_energy_j(profile)[ecu_path], small.path_energy_j(profile)[ecu_path]
        assert e > f or e == f == 0, device   # a profile without power figures prices no energy
