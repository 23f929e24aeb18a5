"""Exit heads that read each row's vertical position (``Candidate.exit_position``): one model
definition, a head that starts as it would without it, costed, exported and run as any other."""

from __future__ import annotations

import dataclasses
import random

import numpy as np
import torch

from explorer.cost import model_cost
from explorer.cost.workloads import candidate_workloads
from explorer.model import build_network
from explorer.model.exits import ExitHead, ExitHeadConfig
from explorer.model.ops import RowPosition
from explorer.space import Candidate, paper_candidate

#: every kind of exit head: encoder exit fusing the LiDAR feature, the ECU exit, decoder exits, residual
PLAIN = dataclasses.replace(paper_candidate(), encoder_exits=(3,), lidar_first=True, exit_residual=True,
                            head_depth=2, head_width=32)
PLACED = dataclasses.replace(PLAIN, exit_position=True)
SIZE = (64, 96)


def _frame(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, 3, *SIZE, generator=g), torch.rand(1, SIZE[1], generator=g) * 6 + 0.5


def test_a_row_position_adds_each_rows_place_from_top_to_bottom_times_its_weights():
    layer = RowPosition(2)
    with torch.no_grad():
        layer.weight.copy_(torch.tensor([1.0, -2.0]))
    out = layer(torch.zeros(1, 2, 5, 3))
    assert out[0, 0, :, 0].tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert out[0, 1, :, 0].tolist() == [2.0, 1.0, 0.0, -1.0, -2.0]
    assert torch.equal(out[..., 0], out[..., 2])    # the same across every column


def test_a_head_starts_as_without_it_and_learns_depth_that_varies_by_row():
    torch.manual_seed(0)
    cfg = ExitHeadConfig(8, 2, 16, 1)
    plain, placed = ExitHead(cfg).eval(), ExitHead(dataclasses.replace(cfg, position=True)).eval()
    placed.load_state_dict(plain.state_dict(), strict=False)
    flat = torch.ones(1, 8, 6, 4)                      # a feature alike in every pixel
    with torch.no_grad():
        torch.testing.assert_close(placed(flat), plain(flat))
        placed.position.weight.fill_(3.0)
        depth = placed(flat)[0, 0]
    assert len({round(float(v), 5) for v in depth[:, 0]}) == 6   # each row its own depth
    assert torch.equal(depth[:, 0], depth[:, -1])


def test_every_exit_head_reads_the_position_and_nothing_else_changes():
    net, twin = build_network(PLACED), build_network(PLAIN)
    heads = [m for m in net.modules() if isinstance(m, ExitHead)]
    assert len(heads) == PLACED.num_paths - 1 and all(isinstance(h.position, RowPosition) for h in heads)
    extra = {k: v.shape for k, v in net.state_dict().items() if k not in twin.state_dict()}
    assert extra and all(k.endswith("position.weight") for k in extra)
    assert {k: v.shape for k, v in twin.state_dict().items()} == {k: net.state_dict()[k].shape for k in twin.state_dict()}


def test_the_field_is_left_out_when_off_and_each_head_pays_for_its_add():
    assert "exit_position" not in PLAIN.to_dict() and PLAIN.key != PLACED.key
    assert PLACED.to_dict()["exit_position"] is True and Candidate.from_dict(PLACED.to_dict()) == PLACED
    adds = [w for w in candidate_workloads(PLACED, (224, 224)) if w.layer.endswith("position")]
    assert len(adds) == PLACED.num_paths - 1 and {w.kind for w in adds} == {"add"}
    plain_cost, placed_cost = model_cost(PLAIN, (224, 224)), model_cost(PLACED, (224, 224))
    assert all(b[0] > a[0] for a, b in zip(plain_cost.path_params_macs()[1:], placed_cost.path_params_macs()[1:]))


def test_exported_graphs_give_the_networks_depth_maps(tmp_path):
    from explorer.deploy.export import export_network
    from explorer.deploy.runtime import AnytimeRunner
    torch.manual_seed(0)
    net = build_network(PLACED).eval()
    for head in (m for m in net.modules() if isinstance(m, ExitHead)):
        torch.nn.init.normal_(head.position.weight)       # trained weights, not the zeros it starts from
    export_network(net, tmp_path / "model", SIZE, devices=("tx2",))
    image, scan = _frame(2)
    with torch.no_grad():
        want = net(image, scan)
    got = AnytimeRunner(tmp_path / "model").depths(image[0].numpy(), scan[0].numpy())
    assert len(got) == len(want)
    for a, b in zip(got, want):
        np.testing.assert_allclose(np.squeeze(a), b.numpy().squeeze(), rtol=1e-4, atol=1e-4)


def _spaces():
    from explorer.space import SearchSpace, load_yaml, resolve_space_path
    base = load_yaml(resolve_space_path("tiny"))
    both = {**base, "exits": {**base["exits"], "position": [False, True]}}
    return SearchSpace.from_dict(base, source="one"), SearchSpace.from_dict(both, source="both")


def test_a_space_lists_heads_reading_the_position_and_its_supernet_holds_their_weights():
    from explorer.supernet import Supernet, random_training_subnet
    from explorer.supernet.network import space_key
    one, both = _spaces()
    assert both.size == 2 * one.size and "exit_position" in both.dimensions()
    assert sorted({c.exit_position for c in both.enumerate()}) == [False, True]
    placed = dataclasses.replace(next(one.enumerate()), exit_position=True)
    assert both.contains(placed) and not one.contains(placed)
    assert space_key(both) != space_key(one)
    assert "exit_position" not in one.dimensions()     # a space without it keeps its key and its draws
    assert {random_training_subnet(both, random.Random(s)).exit_position for s in range(20)} == {False, True}
    net = Supernet(both).eval()
    image, scan = _frame(3)
    sub = net.extract(placed).eval()
    assert any(k.endswith("position.weight") for k in sub.state_dict())
    with torch.no_grad():
        for a, b in zip(net.forward_subnet(placed, image, scan), sub(image, scan)):
            torch.testing.assert_close(a, b)
    twin = net.extract(dataclasses.replace(placed, exit_position=False)).state_dict()
    assert all(torch.equal(v, sub.state_dict()[k]) for k, v in twin.items())
