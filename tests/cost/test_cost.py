
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from explorer.cost import candidate_cost, profile_candidate
from explorer.cost.workloads import candidate_workloads
from explorer.errors import UserError
from explorer.model import build_network
from explorer.space import SearchSpace, fastdepth_candidate, paper_candidate


def _torch_macs(cand, h, w):
    """Multiply-adds of the convolutions and matrix products (the exits' bilinear up-sampling)."""
    net = build_network(cand).eval()
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        net(torch.rand(1, 3, h, w), torch.rand(1, w) + 1)
    return sum(n for op, n in counter.get_flop_counts()["Global"].items()
               if any(name in str(op) for name in ("convolution", "mm", "matmul"))) // 2


@pytest.mark.parametrize("cand", [paper_candidate(), fastdepth_candidate()]
                         + SearchSpace.from_yaml("anytime_depth").random_candidates(2, seed=1))
def test_workloads_match_torch(cand):
    h, w = 224, 224
    wl = candidate_workloads(cand, (h, w))
    assert not any(x.macs for x in wl if x.kind == "resize")   # nearest: no arithmetic
    assert sum(x.macs for x in wl) == _torch_macs(cand, h, w)
    assert sum(x.params for x in wl) == sum(p.numel() for p in build_network(cand).parameters())


def test_workload_fields():
    wl = candidate_workloads(paper_candidate())
    first = wl[1]  # conv0 (after the normalisation)
    assert first.kind == "conv" and first.in_shape == (3, 224, 224) and first.out_shape == (32, 112, 112)
    assert first.macs == 112 * 112 * 32 * 27
    assert first.bytes_written == 32 * 112 * 112 * 4
    kinds = {x.kind for x in wl}
    assert {"conv", "pointwise", "depthwise", "conv1d", "resize", "add", "concat", "slice"} <= kinds


def test_per_path_costs_grow():
    for cand in list(SearchSpace.from_yaml("tiny").enumerate()) + [paper_candidate()]:
        frame = profile_candidate(cand, (64, 64) if cand.stride < 16 else (224, 224), device="tx2")
        for col in ("params", "macs", "latency_ms", "energy_j"):
            assert frame[col].is_monotonic_increasing, (cand, col)
        assert frame.loc[0, "latency_ms"] == 0 and frame.loc[0, "params"] == 0


def test_paper_design_against_table1():
    frame = profile_candidate(paper_candidate())
    p1, p4 = frame.iloc[1], frame.iloc[4]
    assert abs(p1.params / 1.489e6 - 1) <= 0.10
    assert abs(p4.params / 2.014e6 - 1) <= 0.10
    assert abs(p1.macs / 0.319e9 - 1) <= 0.25
    assert abs(p4.macs / 0.594e9 - 1) <= 0.25


def test_input_must_divide_by_stride():
    with pytest.raises(UserError, match="stride"):
        candidate_cost(paper_candidate(), (100, 100))


def test_the_scan_fill_search_grows_with_the_width():
    """Path 0 as a stage finds each column's nearest return in a few passes over the columns: at 640
    columns it moves 640 / 224 times the bytes it moves at 224 (a W x W search would move 8x)."""
    from explorer.model.exits import ScanFill
    from explorer.cost.workloads import trace_stage

    def nearest(w):
        with torch.device("meta"):
            records, _ = trace_stage(ScanFill(), "scan_fill", [torch.empty(1, w), torch.empty(1, 3, 192, w)])
        found = [r for r in records if r.layer.endswith("nearest")]
        assert len(found) == 1 and found[0].in_shape == (w,)
        return found[0].bytes_read + found[0].bytes_written

    assert nearest(640) / nearest(224) == pytest.approx(640 / 224)


def test_tracing_passes_batchnorms_through_and_leaves_the_stage_as_it_was():
    """A BatchNorm is folded (its parameters only count), so tracing skips its arithmetic, most of the
    time of tracing a stage on meta tensors: the counts are the stage's, and afterwards its BatchNorms
    compute again."""
    from explorer.cost.workloads import trace_stage
    from explorer.model.network import stage_specs
    spec = next(s for s in stage_specs(paper_candidate()) if s.inputs == ("image",))
    stage = spec.config.build().eval()
    image = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        before = stage(image)
    records, shapes = trace_stage(stage, spec.name, [image])
    norms = [m for m in stage.modules() if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d))]
    assert norms and not any("forward" in vars(m) for m in norms)
    assert sum(r.params for r in records) == sum(p.numel() for p in stage.parameters())
    with torch.no_grad():
        after = stage(image)
    before, after = (x if isinstance(x, tuple) else (x,) for x in (before, after))
    assert shapes == [tuple(b.shape) for b in before] and all(torch.equal(a, b) for a, b in zip(after, before))
