"""The supernet's stage graphs (``explorer.supernet._graphs``), checked on the CPU by emulation: a
replay runs the stage again on the same static buffers, so the bookkeeping (static inputs and outputs,
gradient accumulators, the parameters a step touched, the BatchNorm statistics a capture's warm-up
moved) is what a CUDA graph would see. The real graphs are measured by python -m benchmarks.gpu --only bench_gpu."""

import random

import pytest
import torch

from explorer.space import SearchSpace
from explorer.supernet import Supernet, SupernetRecipe, largest_candidate, smallest_candidate
from explorer.supernet import train as supernet_train
from explorer.supernet._graphs import StageGraphs
from explorer.training.train import adamw

RECIPE = SupernetRecipe(steps=8, batch_size=4, input_size=(32, 32))


def _batch(seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {"image": torch.rand(4, 3, 32, 32, generator=g), "scan": torch.rand(4, 32, generator=g) * 5,
            "depth": torch.rand(4, 1, 32, 32, generator=g) * 5 + 0.1, "scan_row": torch.full((4,), 16)}


def _train(space, steps, graphs):
    torch.manual_seed(0)
    net = Supernet(space).to(memory_format=torch.channels_last)
    opt = adamw(net.parameters(), 1e-3, 1e-4)
    largest, smallest = largest_candidate(space), smallest_candidate(space)
    losses = []
    for step in steps:
        subnets = supernet_train._subnets(largest, smallest, space, RECIPE, step, random.Random(step))
        losses.append(supernet_train._sandwich_step(net, opt, _batch(step), subnets, RECIPE, torch.device("cpu"),
                                                    0, 1, graphs).tolist())
    return losses, net.state_dict()


@pytest.fixture(scope="module")
def space():
    return SearchSpace.from_yaml("anytime_depth")


def test_training_through_stage_graphs_updates_the_supernet_as_training_without(space):
    # a step while widths stay full, then steps of every width: the heads and widths used differ, so
    # parameters some step leaves alone must get no optimizer update (no gradient) here either
    steps = (0, 6, 7)
    graphs = StageGraphs(emulate=True)
    eager_losses, eager = _train(space, steps, None)
    graph_losses, graphed = _train(space, steps, graphs)
    assert graphs.captures > 0
    assert torch.allclose(torch.tensor(graph_losses), torch.tensor(eager_losses), rtol=1e-6)
    for name, tensor in eager.items():   # BatchNorm statistics too: a capture's warm-up runs are undone
        assert torch.allclose(graphed[name].float(), tensor.float(), atol=1e-6), name


def test_a_stage_seen_before_is_replayed_not_captured(space):
    graphs = StageGraphs(emulate=True)
    _train(space, (6,), graphs)
    captured = graphs.captures
    _train(space, (6,), graphs)      # the same subnets again, on another supernet of the same shapes
    assert captured > 0 and graphs.captures == captured


def test_gradients_reach_only_the_parameters_a_step_used_and_are_cleared_after():
    graphs = StageGraphs(emulate=True)
    used, unused = torch.ones(3, requires_grad=True), torch.ones(3, requires_grad=True)
    x = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    for _ in range(2):
        (out,) = graphs.run("stage", lambda v: (v * used * 2 + 0 * unused.detach(),), [x], [used, unused], [])
        out.sum().backward()
    assert torch.equal(x.grad, torch.full((3,), 4.0))          # the input's gradient flows on through autograd
    graphs.gradients_to()
    assert torch.equal(used.grad, torch.tensor([4.0, 8.0, 12.0]))   # two replays, summed
    assert unused.grad is None
    graphs.clear()
    assert used.grad is None
    (out,) = graphs.run("stage", lambda v: (v * used * 2 + 0 * unused.detach(),), [x], [used, unused], [])
    out.sum().backward()
    graphs.gradients_to()
    assert torch.equal(used.grad, torch.tensor([2.0, 4.0, 6.0])) and graphs.captures == 1


def test_the_least_recently_used_graphs_go_first():
    graphs = StageGraphs(emulate=True, limit=2)
    w = torch.ones(1, requires_grad=True)
    for key in ("a", "b", "a", "c"):
        graphs.run(key, lambda v: (v * w,), [torch.ones(1)], [w], [])
    assert [k[0] for k in graphs.graphs] == ["a", "c"]


def test_the_recipe_keeps_graphs_out_of_its_identity():
    on, off = SupernetRecipe(), SupernetRecipe(cuda_graphs=False)
    assert on.identity() == off.identity()
    assert SupernetRecipe.from_dict(off.to_dict()) == off


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the real graphs; the emulation is above)")
def test_real_cuda_graphs_train_as_training_without_them(space, tmp_path):
    from conftest import TINY_DATA
    from explorer.supernet import read_supernet, train_supernet
    losses = {}
    for graphs in (False, True):
        recipe = SupernetRecipe(steps=8, batch_size=8, input_size=(32, 32), cuda_graphs=graphs)
        path = train_supernet(space, TINY_DATA, recipe, tmp_path / f"{graphs}.pt", torch.device("cuda"))
        history = read_supernet(path)["history"]
        losses[graphs] = torch.tensor([[r["largest"], r["random"]] for r in history])
    # cuDNN's backward kernels sum in no fixed order: the runs agree to rounding, not bit for bit
    assert torch.allclose(losses[True], losses[False], rtol=1e-3), (losses[True], losses[False])


def test_a_stage_that_cannot_be_captured_leaves_the_run_to_train_without_graphs():
    graphs = StageGraphs(emulate=True)
    w = torch.ones(2, requires_grad=True)
    statistics = torch.zeros(2)
    calls = []

    def stage(v):
        calls.append(1)
        statistics.add_(1.0)      # as BatchNorm's running statistics, before the operation that fails
        if len(calls) == 2:
            raise RuntimeError("operation not permitted when stream is capturing")
        return (v * w * 3,)
    with pytest.warns(RuntimeWarning, match="capturing a stage failed"):
        (out,) = graphs.run("stage", stage, [torch.ones(2)], [w], [statistics])
    assert torch.equal(statistics, torch.ones(2))     # the warm-up's two runs undone; the run without graphs kept
    out.sum().backward()
    assert torch.equal(w.grad, torch.full((2,), 3.0))     # through autograd, as without graphs
    (out,) = graphs.run("other", lambda v: (v * w,), [torch.ones(2)], [w], [])
    assert graphs.captures == 0 and "not permitted" in graphs.failed
