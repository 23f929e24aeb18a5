"""Exit heads sized for their position in the supernet: a head slot per position and depth, as wide as
the widest head of the space, whose leading channels a narrower head is; trained by random subnets."""

import dataclasses
import random

import torch

from explorer.model import build_network, stage_specs
from explorer.space import SearchSpace
from explorer.supernet import Supernet, SupernetRecipe, random_training_subnet
from explorer.supernet._slicing import slot_of
from explorer.supernet.network import largest_candidate, smallest_candidate
from explorer.supernet.train import _subnets

SPACE = {
    "image_encoder": {"blocks": [4, 5], "width_mult": [0.25], "exits": [3]},
    "lidar_encoder": {"depth": [4], "width": [8]},
    "ecu": {"enabled": [True], "band": [1], "width": [16]},
    "decoder": {"widths": [[32, 24], [16], [8, 4]]},
    "exits": {"optional": [0, 2], "head_depth": [1], "head_width": [8], "ecu_head_depth": [1, 2],
              "ecu_head_width": [4, 16], "encoder_head_depth": [2], "encoder_head_width": [4, 8]}}


def _inputs(n=2, size=32):
    g = torch.Generator().manual_seed(0)
    return torch.rand(n, 3, size, size, generator=g), torch.rand(n, size, generator=g) * 4 + 0.5


def test_every_position_and_depth_has_a_slot_as_wide_as_its_widest_head():
    space = SearchSpace.from_dict(SPACE, "heads")
    net = Supernet(space)
    for name in ("exit_0_d1", "exit_0_d2", "exit_b3_d2", "exit_2_d1", "exit_3_d1"):
        assert name in net.slots, name
    assert net.slots["exit_0_d2"].layers[0].out_channels == 16
    for cand in space.random_candidates(12, seed=0):
        assert all(slot_of(s) in net.slots for s in stage_specs(cand))


def test_a_per_position_head_subnet_is_a_stand_alone_network_with_the_same_weights():
    space = SearchSpace.from_dict(SPACE, "heads")
    net = Supernet(space)
    image, scan = _inputs()
    net.train()
    net(image, scan)
    net.eval()
    for p in net.parameters():
        p.data.normal_(0, 0.1)
    base = dataclasses.replace(random_training_subnet(space, random.Random(3)), exits=(0, 2, 3), encoder_exits=(3,))
    for ecu_head in ((2, 4), (2, 16), (1, 0)):
        cand = dataclasses.replace(base, ecu_head_depth=ecu_head[0], ecu_head_width=ecu_head[1],
                                   encoder_head_depth=2, encoder_head_width=4)
        assert cand.head("ecu") == ecu_head and space.contains(cand)
        alone = build_network(cand).eval()
        alone.load_state_dict(net.extract(cand).state_dict())
        with torch.no_grad():
            sliced = net.forward_subnet(cand, image, scan)
            own = alone(image, scan)
        assert len(sliced) == cand.num_paths
        assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(sliced, own))


def test_training_subnets_draw_the_heads_of_each_position():
    space = SearchSpace.from_dict(SPACE, "heads")
    recipe = SupernetRecipe(steps=6, batch_size=8, input_size=(32, 32), random_subnets=2)
    rng = random.Random(0)
    subnets = [c for step in range(8) for c in _subnets(largest_candidate(space), smallest_candidate(space),
                                                          space, recipe, step, rng)]
    assert {c.head("ecu") for c in subnets} >= {(1, 0), (2, 4), (2, 16)}
    assert {c.head("encoder") for c in subnets} >= {(2, 4), (2, 8)}
    # a space without heads sized per position draws what it drew before
    plain = SearchSpace.from_dict({**SPACE, "exits": {"optional": [0, 2], "head_depth": [1], "head_width": [8]}})
    assert random_training_subnet(plain, random.Random(5)).ecu_head_depth == 0


def test_a_per_position_head_subnet_trains_and_is_evaluated_stage_by_stage(tmp_path):
    from conftest import TINY_DATA
    from explorer.data import open_dataset
    from explorer.supernet import train_supernet
    from explorer.supernet.evaluators import SupernetEvaluator
    space = SearchSpace.from_dict(SPACE, "heads")
    file = train_supernet(space, TINY_DATA, SupernetRecipe(steps=2, batch_size=8, input_size=(32, 32)),
                          tmp_path / "s.pt")
    train = open_dataset(TINY_DATA, "train", (32, 32), train_augment=False)
    val = open_dataset(TINY_DATA, "val", (32, 32))
    args = (file, space, train, val, torch.device("cpu"))
    shared = SupernetEvaluator(*args, calibration_images=8, batch_size=8)
    alone = SupernetEvaluator(*args, calibration_images=8, batch_size=8, stagewise=False)
    base = dataclasses.replace(random_training_subnet(space, random.Random(3)), exits=(0, 2, 3), encoder_exits=(3,))
    for width in (4, 16):
        cand = dataclasses.replace(base, ecu_head_depth=2, ecu_head_width=width)
        a, b = shared(cand), alone(cand)
        assert list(a.metrics["path"]) == list(b.metrics["path"]) == list(range(cand.num_paths))
        assert (a.metrics["rmse"] - b.metrics["rmse"]).abs().max() < 1e-4, cand


def test_progressive_shrinking_starts_every_positions_heads_at_full_width():
    from explorer.supernet.train import _full_width
    space = SearchSpace.from_dict(SPACE, "heads")
    largest = largest_candidate(space)
    assert largest.head("ecu") == (2, 16) and largest.head("encoder") == (2, 8)
    for seed in range(6):
        full = _full_width(random_training_subnet(space, random.Random(seed)), largest)
        assert full.head("ecu") in ((1, 0), (2, 16)) and full.head("encoder") == (2, 8)
    plain = SearchSpace.from_dict({**SPACE, "exits": {"optional": [0, 2], "head_depth": [1, 2], "head_width": [8]}})
    sub = random_training_subnet(plain, random.Random(1))
    assert _full_width(sub, largest_candidate(plain)) == dataclasses.replace(
        sub, width_mult=0.25, decoder_widths=largest_candidate(plain).decoder_widths,
        head_width=8 if sub.head_depth == 2 else 0)
