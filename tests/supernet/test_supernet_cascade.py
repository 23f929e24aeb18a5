"""Cascade exits in the supernet: heads of their own kind (they learn a correction of the previous exit,
not of the scan), sliced like any subnet, trained in the head-kind rotation, evaluated stage by stage."""

import dataclasses
import random

import pytest
import torch

from conftest import TINY_DATA
from explorer.data import open_dataset
from explorer.model import build_network, stage_specs
from explorer.space import SearchSpace
from explorer.supernet import Supernet, SupernetRecipe, random_training_subnet, train_supernet
from explorer.supernet._slicing import slot_of
from explorer.supernet.evaluators import SupernetEvaluator
from explorer.supernet.network import head_kinds
from explorer.supernet.train import _subnets

SPACE = {
    "image_encoder": {"blocks": [4, 5], "width_mult": [0.25], "exits": [3]},
    "lidar_encoder": {"depth": [4], "width": [8]},
    "ecu": {"enabled": [True], "band": [1], "width": [16]},
    "decoder": {"widths": [[32, 24], [16], [8, 4]]},
    "exits": {"optional": [0, 2], "head_depth": [1, 2], "head_width": [8], "lidar_only": [False, True],
              "residual": [False, True], "cascade": [False, True]}}


@pytest.fixture(scope="module")
def space():
    return SearchSpace.from_dict(SPACE, "cascade")


def _inputs(n=2, size=32):
    g = torch.Generator().manual_seed(0)
    return torch.rand(n, 3, size, size, generator=g), torch.rand(n, size, generator=g) * 4 + 0.5


def _cascade(space, **changes):
    base = random_training_subnet(space, random.Random(3))
    return dataclasses.replace(base, exit_residual=True, exit_cascade=True, **changes)


def test_cascade_heads_are_their_own_kind_and_a_cascades_first_exit_is_a_scan_correction(space):
    net = Supernet(space)
    assert {(d, r, c) for d, r, c in head_kinds(space)} == {(d, r, c) for d in (1, 2)
                                                           for r, c in ((False, False), (True, False), (True, True))}
    for lidar_exit in (True, False):
        cand = _cascade(space, lidar_exit=lidar_exit)
        slots = [slot_of(s) for s in stage_specs(cand) if s.path is not None]
        assert slots[0].endswith("_r") and all(s.endswith("_c") for s in slots[1:])
        assert all(s in net.slots for s in slots)
    # the same backbone, other head weights than the residual subnet's, but for its first exit
    cascade = _cascade(space, lidar_exit=False)
    residual = dataclasses.replace(cascade, exit_cascade=False)
    a, b = net.subnet_tensors(cascade), net.subnet_tensors(residual)
    assert set(a) == set(b)
    first = next(s.name for s in stage_specs(cascade) if s.path is not None)
    for k in a:
        if not a[k].dim():
            continue
        if k.startswith(("stages.exit", "stages.lidar_exit")):   # a head: the same tensor for the first exit alone
            assert (a[k].data_ptr() == b[k].data_ptr()) == k.startswith(f"stages.{first}."), k
        else:
            assert torch.equal(a[k], b[k]), k


def test_a_cascade_subnet_is_a_stand_alone_network_with_the_same_weights(space):
    net = Supernet(space)
    image, scan = _inputs()
    net.train()
    net(image, scan)   # statistics away from their initial values
    net.eval()
    for p in net.parameters():
        p.data.normal_(0, 0.1)
    for lidar_exit in (True, False):
        cand = _cascade(space, lidar_exit=lidar_exit)
        alone = build_network(cand).eval()
        alone.load_state_dict(net.extract(cand).state_dict())
        with torch.no_grad():
            sliced = net.forward_subnet(cand, image, scan)
            own = alone(image, scan)
        assert len(sliced) == cand.num_paths
        assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(sliced, own))
        # each path builds on the one before: not the residual network's paths
        residual = net.forward_subnet(dataclasses.replace(cand, exit_cascade=False), image, scan)
        assert not torch.allclose(residual[-1], sliced[-1])


def test_the_rotation_trains_cascade_heads(space):
    from explorer.supernet.network import largest_candidate, smallest_candidate
    recipe = SupernetRecipe(steps=6, batch_size=8, input_size=(32, 32), random_subnets=1)
    rng = random.Random(0)
    seen = {(c.head_depth, c.exit_residual, c.exit_cascade)
            for step in range(6)
            for c in _subnets(largest_candidate(space), smallest_candidate(space), space, recipe, step, rng)}
    assert seen == set(head_kinds(space))


def test_a_cascade_is_evaluated_stage_by_stage_as_a_whole_network(space, tmp_path):
    file = train_supernet(space, TINY_DATA, SupernetRecipe(steps=2, batch_size=8, input_size=(32, 32)),
                          tmp_path / "s.pt")
    train = open_dataset(TINY_DATA, "train", (32, 32), train_augment=False)
    val = open_dataset(TINY_DATA, "val", (32, 32))
    args = (file, space, train, val, torch.device("cpu"))
    shared = SupernetEvaluator(*args, calibration_images=8, batch_size=8)
    alone = SupernetEvaluator(*args, calibration_images=8, batch_size=8, stagewise=False)
    cascade = _cascade(space, lidar_exit=False, head_depth=2, head_width=8)
    # the residual network first: the cascade's first exit is then a leaf in the memo, with no outputs kept
    for cand in (dataclasses.replace(cascade, exit_cascade=False), cascade, _cascade(space, lidar_exit=True)):
        a, b = shared(cand), alone(cand)
        assert list(a.metrics["path"]) == list(b.metrics["path"]) == list(range(cand.num_paths))
        assert (a.metrics["rmse"] - b.metrics["rmse"]).abs().max() < 1e-4, cand
