"""The paper's reference networks: built in torch, costed by the workload tracer, and the TX2
profile fitted on their published figures."""

import json

import pytest
import torch
import yaml
from torch.utils.flop_counter import FlopCounterMode

from explorer.cost import dilated_count_macs, get_device, profile_reference, reference_workloads
from explorer.errors import UserError
from explorer.model.reference import REFERENCES

CONV_KINDS = {"conv", "pointwise", "pointwise_1ch", "depthwise", "conv1d", "deconv"}


@pytest.mark.parametrize("name", [n for n in REFERENCES if n != "s2d-resnet50-upproj"])
def test_traced_params_and_macs_match_torch(name):
    ref = REFERENCES[name]
    torch.manual_seed(0)
    net = ref.build().eval()
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        net(torch.rand(ref.input_shape((64, 96))))
    wl = reference_workloads(name, (64, 96))
    assert sum(w.params for w in wl) == sum(p.numel() for p in net.parameters())
    # flop_counter counts 2 FLOPs per multiply-add of (transposed) convolutions; resizes it skips
    assert sum(w.macs for w in wl if w.kind in CONV_KINDS) * 2 == counter.get_total_flops()


#: Paper GFLOPs we do not meet within 10%, and why (explorer/model/reference.py says more).
GFLOPS_EXPLAINED = {"fastdepth": "paper 0.867 vs FastDepth's own 0.74 GMACs"}


@pytest.mark.parametrize("name", [n for n, r in REFERENCES.items() if r.paper])
def test_against_paper_tables(name):
    paper = REFERENCES[name].paper
    frame = profile_reference(name, paper.input_size)
    assert frame["params"][0] / 1e6 == pytest.approx(paper.params_m, rel=0.10)
    # the paper counts transposed convolutions dilated; for networks without them that is the plain count
    gmacs = frame.get("macs_dilated", frame["macs"])[0] / 1e9
    if name in GFLOPS_EXPLAINED:
        assert gmacs < paper.gflops  # the explained gap: ours is the lower, exact count
    else:
        assert gmacs == pytest.approx(paper.gflops, rel=0.10)


@pytest.mark.parametrize("name", ["s2d-resnet50", "s2d-resnet18"])
def test_sparse_to_dense_gflops_are_dilated_transposed_convolutions(name):
    paper = REFERENCES[name].paper
    wl = reference_workloads(name, paper.input_size)
    deconv = [w for w in wl if w.kind == "deconv"]
    assert len(deconv) == 4 and all(w.kernel == 2 and w.stride == 2 for w in deconv)
    real = sum(w.macs for w in wl)
    assert dilated_count_macs(wl) == real + 3 * sum(w.macs for w in deconv)  # 2x2 stride 2: 4x each
    assert dilated_count_macs(wl) / 1e9 == pytest.approx(paper.gflops, rel=0.01)
    assert real / 1e9 < 0.96 * paper.gflops


def test_tx2_meets_every_paper_figure():
    from explorer.cost import candidate_cost
    from explorer.cost.fit import PAPER_TX2_PATHS_MS, TX2_REFERENCES
    from explorer.space import paper_candidate
    tx2 = get_device("tx2")
    published = candidate_cost(paper_candidate(), paper_graph=True)   # the graph the paper measured
    for got, want in zip(published.path_latency_ms(tx2)[1:], PAPER_TX2_PATHS_MS):
        assert abs(got / want - 1) <= 0.10
    for name in TX2_REFERENCES:
        paper = REFERENCES[name].paper
        got = profile_reference(name, paper.input_size, tx2)["latency_ms"][0]
        assert abs(got / paper.latency_ms - 1) <= 0.10, name
    recorded = {c["what"] for c in tx2.provenance["checks"]}
    assert {f"paper design path {i}" for i in range(1, 5)} <= recorded and len(recorded) == 8


def test_memory_bound_layers_grow_with_the_input():
    from explorer.cost import candidate_cost
    from explorer.space import paper_candidate
    tx2 = get_device("tx2")
    small = candidate_cost(paper_candidate(), (224, 224))
    big = candidate_cost(paper_candidate(), (224, 896))
    resize = [sum(tx2.layer_ms(w) for w in c.workloads if w.kind == "resize") for c in (small, big)]
    assert resize[1] > 3.5 * resize[0]
    ratio = big.path_latency_ms(tx2)[-1] / small.path_latency_ms(tx2)[-1]
    assert 2.8 < ratio < 4.0   # 4x the pixels: fixed launch costs keep it under 4x, but not far


def test_profile_without_optional_kind_still_loads(tmp_path):
    data = get_device("tx2").to_dict()
    del data["kinds"]["deconv"]
    f = tmp_path / "old.yaml"
    f.write_text(yaml.safe_dump(data))
    old = get_device(str(f))
    assert old.kinds["deconv"] == old.kinds["conv"]
    assert profile_reference("s2d-resnet18", (64, 64), old)["latency_ms"][0] > 0


def test_weight_traffic_false_prices_activations_only(tmp_path):
    from explorer.cost.workloads import BYTES_PER_VALUE
    tx2 = get_device("tx2")
    assert tx2.kinds["deconv"].weight_traffic is False and tx2.kinds["conv"].weight_traffic is True
    deconv = next(w for w in reference_workloads("s2d-resnet50", (228, 304)) if w.kind == "deconv")
    k = tx2.kinds["deconv"]
    activations = deconv.bytes_read + deconv.bytes_written - deconv.params * BYTES_PER_VALUE
    memory = activations / (k.bandwidth_gbs * 1e6)
    assert tx2.layer_ms(deconv) == pytest.approx(k.overhead_ms + max(memory, deconv.macs / (k.gmacs * 1e6)))
    data = tx2.to_dict()
    assert data["kinds"]["deconv"]["weight_traffic"] is False and "weight_traffic" not in data["kinds"]["conv"]
    data["kinds"]["deconv"]["weight_traffic"] = True
    f = tmp_path / "weights.yaml"
    f.write_text(yaml.safe_dump(data))
    assert get_device(str(f)).layer_ms(deconv) > tx2.layer_ms(deconv)   # 2 M weights read as well
    data["kinds"]["deconv"]["weight_traffic"] = "sometimes"
    f.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match="weight_traffic must be true or false"):
        get_device(str(f))


def test_cli_profile_reference_json_and_unknown_name(run_cli):
    code, out, _ = run_cli("profile", "s2d-resnet50", "--device", "tx2", "--input-size", "228x304", "--json")
    data = json.loads(out)
    assert code == 0 and data["reference"] == "s2d-resnet50"
    assert data["paths"][0]["params"] == pytest.approx(28.39e6, rel=0.01)
    assert data["paths"][0]["latency_ms"] == pytest.approx(554.7, rel=0.10)
    assert data["paths"][0]["macs_dilated"] / 1e9 == pytest.approx(8.910, rel=0.01)
    code, out, err = run_cli("profile", "resnet-9000", "--device", "tx2")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "s2d-resnet18" in err and "monodepth2-resnet18" in err


def test_unsuitable_input_is_a_user_error():
    with pytest.raises(UserError, match="multiples of 32"):
        reference_workloads("fastdepth", (100, 100))


def test_fit_reproduces_shipped_profiles(shared_data, tmp_path):
    from explorer.cost.fit import PROFILES_DIR, rebuild
    rebuild(shared_data, tmp_path)
    for name in ("tx2", "tx2-cpu", "rpi4"):
        fitted = yaml.safe_load((tmp_path / f"{name}.yaml").read_text())
        shipped = yaml.safe_load((PROFILES_DIR / f"{name}.yaml").read_text())
        for key in ("bandwidth_gbs", "inference_overhead_ms"):
            assert fitted[key] == pytest.approx(shipped[key], rel=1e-3), (name, key)
        for kind, cost in shipped["kinds"].items():
            for field, value in cost.items():
                want = value if isinstance(value, bool) else pytest.approx(value, rel=1e-3)
                assert fitted["kinds"][kind][field] == want, (name, kind, field)
        assert fitted["provenance"]["checks"] == shipped["provenance"]["checks"]


@pytest.mark.parametrize("name", ["s2d-resnet18", "monodepth2-resnet18", "fastdepth-pruned"])
def test_reference_trains_as_a_two_path_network(name):
    from explorer.model.exits import interpolate_scan
    from explorer.model.reference import ReferenceDepthNet
    from explorer.training.train import multi_exit_loss
    torch.manual_seed(0)
    net = ReferenceDepthNet(name)
    image, scan = torch.rand(2, 3, 64, 96), torch.rand(2, 96) * 5
    outs = net(image, scan, 40)
    assert [tuple(o.shape) for o in outs] == [(2, 1, 64, 96)] * 2 and net.candidate.num_paths == 2
    assert torch.equal(outs[0], interpolate_scan(scan, 64))
    if name.startswith("monodepth2"):   # disparity turned into depth within MonoDepth2's range
        assert float(outs[1].min()) >= 0.1 - 1e-5 and float(outs[1].max()) <= 100 + 1e-3
    loss, _ = multi_exit_loss(outs, torch.rand(2, 1, 64, 96) * 5)
    loss.backward()
    # MonoDepth2's coarser disparity heads (scales 1-3) serve its self-supervised loss, not the output
    coarse = ("disp.1.", "disp.2.", "disp.3.")
    assert all((p.grad is not None) != k.startswith(coarse) for k, p in net.network.named_parameters())


def test_sparse_to_dense_sees_the_scan_on_its_row():
    from explorer.model.reference import ReferenceDepthNet
    net = ReferenceDepthNet("s2d-resnet18").eval()
    seen = []
    net.network.encoder.register_forward_pre_hook(lambda m, args: seen.append(args[0]))
    scan = torch.arange(1, 97, dtype=torch.float32)[None]
    with torch.no_grad():
        net(torch.rand(1, 3, 64, 96), scan, 40)
    sparse = seen[0][0, 3]
    assert torch.equal(sparse[40], scan[0]) and float(sparse.abs().sum()) == float(scan.sum())
