"""A network that works below its input size (``Candidate.downscale``): one model definition at a
fraction of the frame, exits back at the frame's size, costed, exported and run as any other."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from explorer.cost import model_cost
from explorer.cost.workloads import candidate_workloads
from explorer.errors import UserError
from explorer.model import build_network
from explorer.model.downscale import FirstReturns
from explorer.space import Candidate, SearchSpace, check_size, load_yaml, paper_candidate, resolve_space_path
from explorer.supernet.network import space_key

#: every kind of stage a downscaled network reads differently: encoder exit, LiDAR-only exit, residual heads
HALF = dataclasses.replace(paper_candidate(), downscale=2, encoder_exits=(3,), lidar_exit=True, exit_residual=True)
SIZE = (64, 96)


def _frame(seed: int = 0, size=SIZE):
    g = torch.Generator().manual_seed(seed)
    scan = torch.rand(1, size[1], generator=g) * 6 + 0.5
    scan[:, ::3] = 0   # columns without a return
    return torch.rand(1, 3, *size, generator=g), scan


def test_first_returns_keeps_the_first_column_with_a_return_of_each_group():
    scan = torch.tensor([[0.0, 1.0, 2.0, 3.0, 0.0, 0.0, 5.0, 0.0]])
    assert FirstReturns(2)(scan).tolist() == [[1.0, 2.0, 0.0, 5.0]]
    assert FirstReturns(4)(scan).tolist() == [[1.0, 5.0]]


def test_every_path_comes_back_at_the_input_size_and_the_working_stages_see_a_smaller_frame():
    net = build_network(HALF).eval()
    image, scan = _frame()
    seen = {}

    def saw(name):
        def hook(module, args, out):
            seen[name] = tuple(args[0].shape)
        return hook
    net.stages["image_encoder"].register_forward_hook(saw("image"))
    net.stages["lidar_encoder"].register_forward_hook(saw("scan"))
    with torch.no_grad():
        depths = net(image, scan)
    assert len(depths) == HALF.num_paths
    assert all(d.shape == (1, 1, *SIZE) for d in depths)
    assert seen == {"image": (1, 3, 32, 48), "scan": (1, 48)}


def test_the_downscaled_network_has_the_weights_of_its_twin_at_full_size():
    half = build_network(HALF)
    full = build_network(dataclasses.replace(HALF, downscale=1))
    assert {k: v.shape for k, v in half.state_dict().items()} == {k: v.shape for k, v in full.state_dict().items()}


def test_a_slanted_scan_line_finds_its_feature_rows_at_the_stride_of_the_input():
    net = build_network(HALF).eval()
    image, scan = _frame(1)
    rows = torch.full(scan.shape, 40, dtype=torch.int64)
    with torch.no_grad():
        by_row, by_column = net(image, scan, 40), net(image, scan, rows)
    for a, b in zip(by_row, by_column):
        torch.testing.assert_close(a, b)


def test_it_costs_less_than_its_twin_and_pays_for_its_resize():
    twin = dataclasses.replace(HALF, downscale=1)
    half_macs, twin_macs = (model_cost(c, (224, 224)).path_params_macs()[-1][1] for c in (HALF, twin))
    assert half_macs < twin_macs / 3
    first = [w for w in candidate_workloads(HALF, (224, 224)) if w.stage == "downscale"]
    assert [(w.kind, w.in_shape, w.out_shape) for w in first] == [
        ("resize", (3, 224, 224), (3, 112, 112)), ("slice", (224,), (112,))]


def test_its_input_sides_divide_by_the_stride_times_the_downscale():
    assert HALF.stride == 32 and HALF.working_stride == 16
    check_size((64, 96), HALF.stride, "--input-size")
    with pytest.raises(UserError, match="multiples of the encoder stride 32"):
        check_size((48, 48), HALF.stride, "--input-size")


def test_the_field_is_left_out_at_the_input_size_and_refused_outside_its_choices():
    assert "downscale" not in paper_candidate().to_dict()
    assert HALF.to_dict()["downscale"] == 2 and Candidate.from_dict(HALF.to_dict()) == HALF
    with pytest.raises(UserError, match="downscale=3 is not one of"):
        dataclasses.replace(paper_candidate(), downscale=3)


def test_a_space_lists_working_sizes_and_they_do_not_change_its_supernet():
    base = load_yaml(resolve_space_path("tiny"))
    one = SearchSpace.from_dict(base, source="one")
    both = SearchSpace.from_dict({**base, "downscale": [1, 2]}, source="both")
    assert both.size == 2 * one.size
    assert sorted({c.downscale for c in both.enumerate()}) == [1, 2]
    assert both.contains(dataclasses.replace(next(one.enumerate()), downscale=2))
    assert not one.contains(dataclasses.replace(next(one.enumerate()), downscale=2))
    assert space_key(both) == space_key(one)
    with pytest.raises(UserError, match=r"downscale \[3\]"):
        SearchSpace.from_dict({**base, "downscale": [1, 3]}, source="bad")


def test_exported_graphs_give_the_networks_depth_maps(tmp_path):
    from explorer.deploy.export import export_network
    from explorer.deploy.runtime import AnytimeRunner
    torch.manual_seed(0)
    net = build_network(HALF).eval()
    export_network(net, tmp_path / "model", SIZE, devices=("tx2",))
    runner = AnytimeRunner(tmp_path / "model")
    image, scan = _frame(2)
    with torch.no_grad():
        want = net(image, scan)
    got = runner.depths(image[0].numpy(), scan[0].numpy())
    assert len(got) == len(want)
    for a, b in zip(got, want):
        np.testing.assert_allclose(np.squeeze(a), b.numpy().squeeze(), rtol=1e-4, atol=1e-4)
