"""Precision as a search dimension: profiles that price int8 graphs, spaces that list
``precision: [fp32, int8]``, int8 candidates costed at int8 and measured after quantization."""

import dataclasses
import json

import pytest
import yaml

from conftest import TINY_DATA
from explorer.cost import candidate_cost, get_device
from explorer.cost.devices import DeviceProfile
from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace, paper_candidate
from explorer.study.records import trial_record

TINY_INT8 = {**yaml.safe_load(open(SearchSpace.from_yaml("tiny").source).read()), "name": "tiny8",
             "precision": ["fp32", "int8"]}


def _with_int8(tmp_path, slower: float = 2.0):
    """tx2 with an int8 section whose every layer takes ``slower`` times as long as in fp32."""
    data = get_device("tx2").to_dict()
    data["name"] = "tx2-int8"
    data["int8"] = {"bandwidth_gbs": data["bandwidth_gbs"] / slower,
                    "kinds": {k: {**v, "gmacs": v["gmacs"] / slower, "overhead_ms": v["overhead_ms"] * slower,
                                  **({"bandwidth_gbs": v["bandwidth_gbs"] / slower} if v.get("bandwidth_gbs") else {})}
                              for k, v in data["kinds"].items()}}
    f = tmp_path / "tx2-int8.yaml"
    f.write_text(yaml.safe_dump(data))
    return f


def test_a_profile_prices_int8_only_where_it_has_int8_rates(tmp_path):
    tx2 = get_device("tx2")
    assert tx2.precisions == ("fp32",)
    with pytest.raises(UserError, match="prices no int8"):
        tx2.at_precision("int8")
    dev = get_device(_with_int8(tmp_path))
    assert dev.precisions == ("fp32", "int8") and dev.int8.inference_overhead_ms == tx2.inference_overhead_ms
    again = DeviceProfile.from_dict(yaml.safe_load(dev.to_yaml()), "again")
    assert again.int8.kinds["pointwise"].gmacs == pytest.approx(dev.int8.kinds["pointwise"].gmacs, rel=1e-5)
    fp32, int8 = paper_candidate(), dataclasses.replace(paper_candidate(), precision="int8")
    a, b = candidate_cost(fp32).path_latency_ms(dev), candidate_cost(int8).path_latency_ms(dev)
    assert a == candidate_cost(fp32).path_latency_ms(tx2)       # fp32 candidates: the fp32 rates
    assert b == a      # int8 twice as slow: an int8 export keeps every stage graph fp32, and so does the price
    faster = get_device(_with_int8(tmp_path, slower=0.5))
    c = candidate_cost(int8).path_latency_ms(faster)
    assert all(y < x for x, y in zip(a[1:], c[1:]))               # int8 twice as fast: the int8 rates
    bad = get_device("tx2").to_dict()
    bad["int8"] = {"gmacs": 3}
    with pytest.raises(UserError, match="'int8' must be a mapping with its own 'kinds'"):
        DeviceProfile.from_dict(bad, "bad.yaml")


def test_precision_is_a_dimension_of_a_space():
    space = SearchSpace.from_dict(TINY_INT8, "tiny8")
    plain = SearchSpace.from_yaml("tiny")
    assert space.size == 2 * plain.size == len(list(space.enumerate()))
    assert {c.precision for c in space.enumerate()} == {"fp32", "int8"}
    assert "precision" in space.dimensions() and "precision" not in plain.dimensions()
    c = next(c for c in space.enumerate() if c.precision == "int8")
    assert space.contains(c) and not plain.contains(c) and c.describe().endswith("int8")
    assert Candidate.from_dict(c.to_dict()) == c
    assert "precision" not in paper_candidate().to_dict()       # fp32 keys stay what they were
    with pytest.raises(UserError, match=r"precision \['int4'\] unknown"):
        SearchSpace.from_dict({**TINY_INT8, "precision": ["int4"]}, "bad")


@pytest.mark.slow
def test_a_search_measures_int8_candidates_after_quantization(tmp_path, run_cli):
    from explorer.study.results import trial_path_costs
    from explorer.study.search import SearchConfig, SearchRun, search
    space = tmp_path / "tiny8.yaml"
    space.write_text(yaml.safe_dump(TINY_INT8))
    device = _with_int8(tmp_path, slower=0.5)   # int8 pays in every stage graph
    cfg = SearchConfig(study="p8", space=str(space), device=str(device), data=TINY_DATA, train_size=(32, 32),
                       input_size=(64, 64), batch_size=8, val_limit=8, evaluator="supernet", supernet_steps=4,
                       finalists=0, baselines=())
    out = search(cfg.resolve(), SearchRun(n_trials=12, timeout_s=None, reports=tmp_path))
    done = [t for t in out.study.trials if "path_metrics" in t.user_attrs]
    int8 = [t for t in done if t.user_attrs["candidate"].get("precision") == "int8"]
    fp32 = [t for t in done if t.user_attrs["candidate"].get("precision", "fp32") == "fp32"]
    assert int8 and fp32
    for t in int8:
        q, pm, before = t.user_attrs["quantization"], t.user_attrs["path_metrics"], t.user_attrs["path_metrics_fp32"]
        assert len(q["rmse_degradation"]) == len(pm) == len(before) and q["frames"] == 8
        for d, m, b in zip(q["rmse_degradation"], pm, before):   # the estimate scaled by what int8 did
            assert m["rmse"] == pytest.approx(b["rmse"] * (1 + d), rel=1e-6)
        assert any(abs(d) > 0 for d in q["rmse_degradation"][1:])
        cand = Candidate.from_dict(trial_record(t).shipped_candidate)   # the network as it ships
        assert t.user_attrs["int8_graphs"] == list(candidate_cost(cand, (64, 64)).int8_graphs(get_device(device)))
        assert len(t.user_attrs["int8_graphs"]) == cand.num_paths - 1   # every stage graph but path 0's
        assert t.user_attrs["latency_ms"] == pytest.approx(candidate_cost(cand, (64, 64)).path_latency_ms(get_device(device)))
        assert trial_path_costs(t, get_device(device), "time") == pytest.approx(t.user_attrs["latency_ms"])
    assert all("quantization" not in t.user_attrs for t in fp32)
    # an int8 trial exports as int8 unless told otherwise
    trial = int8[0]
    code, text, err = run_cli("export", "--study", "p8", "--trial", trial.number, "--out", tmp_path / "m8",
                              "--reports", tmp_path, "--device", device)
    assert code == 0, err
    graphs = trial.user_attrs["int8_graphs"]
    assert f"int8 stage graphs: {len(graphs)} of {len(graphs) + 1}" in text.replace("\n", " ")
    manifest = json.loads((tmp_path / "m8" / "manifest.json").read_text())
    assert manifest["precision"] == "int8" and manifest["candidate"]["precision"] == "int8"
    # the stage graphs the search priced int8, and no timing here
    assert [s["name"] for s in manifest["stages"] if s["precision"] == "int8"] == trial.user_attrs["int8_graphs"]
    assert not any("ms_here" in s for s in manifest["stages"])
    assert manifest["expected_cost_precision"] == "int8" and "expected_cost_note" not in manifest   # priced int8
    # its anytime curve is predicted at int8 where the profile can, else at fp32 and said so
    for dev, priced in ((device, "int8"), ("tx2", "fp32")):
        code, text, err = run_cli("curve", tmp_path / "m8", "--data", TINY_DATA, "--device", dev, "--frames", "2",
                                  "--deadlines", "3")
        assert code == 0, err
        assert json.loads((tmp_path / "m8" / "anytime_curve.json").read_text())["priced_precision"] == priced
        assert ("the model is int8" in text) == (priced == "fp32")


def test_an_int8_space_on_a_profile_without_int8_rates_is_one_line(tmp_path, run_cli):
    space = tmp_path / "tiny8.yaml"
    space.write_text(yaml.safe_dump(TINY_INT8))
    code, out, err = run_cli("search", "--space", space, "--device", "tx2", "--data", TINY_DATA,
                             "--reports", tmp_path, "--trials", "1")
    assert code == 2 and "prices no int8 graphs" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "tx2-tiny8").exists()


def test_an_int8_space_shares_the_supernet_of_its_fp32_twin():
    from explorer.supernet.network import space_key
    assert space_key(SearchSpace.from_dict(TINY_INT8, "tiny8")) == space_key(SearchSpace.from_yaml("tiny"))


def test_an_int8_finalist_is_retrained_then_measured_after_quantization(tmp_path):
    from explorer.study.finalists import finalist_trials
    from explorer.study.search import SearchConfig, SearchRun, search
    space = tmp_path / "only8.yaml"
    space.write_text(yaml.safe_dump({**TINY_INT8, "name": "only8", "precision": ["int8"]}))
    cfg = SearchConfig(study="f8", space=str(space), device=str(_with_int8(tmp_path)), data=TINY_DATA,
                       train_size=(32, 32), input_size=(64, 64), batch_size=8, val_limit=8, evaluator="supernet",
                       supernet_steps=4, finalists=1, finalist_steps=3, baselines=())
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    (fin,) = finalist_trials(out.study)
    assert fin.user_attrs["candidate"]["precision"] == "int8"
    before, after = fin.user_attrs["path_metrics_fp32"], fin.user_attrs["path_metrics"]
    for d, m, b in zip(fin.user_attrs["quantization"]["rmse_degradation"], after, before):
        assert m["rmse"] == pytest.approx(b["rmse"] * (1 + d), rel=1e-6)


def test_an_int8_candidate_is_priced_at_int8_only_in_the_stage_graphs_where_it_pays(tmp_path):
    """As an int8 export keeps a stage graph (the stages between two exits) int8 only where it runs at
    most INT8_KEEP_RATIO of its fp32 time, the price takes int8 only there."""
    from explorer.cost.devices import _stage_ms
    from explorer.cost.precision import INT8_KEEP_RATIO
    data = get_device("tx2").to_dict()
    # int8 convolutions 4x as fast, resizes 20x as slow: the encoder pays, the decoders do not
    bandwidth = data["bandwidth_gbs"]
    data["int8"] = {"kinds": {k: {**v, "gmacs": v["gmacs"] * 4, "bandwidth_gbs": v.get("bandwidth_gbs", bandwidth) * 4}
                              if k in ("pointwise", "depthwise", "conv") else
                              {**v, "bandwidth_gbs": v.get("bandwidth_gbs", bandwidth) / 20,
                               "overhead_ms": v["overhead_ms"] * 20} if k == "resize" else v
                              for k, v in data["kinds"].items()}}
    (tmp_path / "d.yaml").write_text(yaml.safe_dump({**data, "name": "mixed"}))
    dev = get_device(tmp_path / "d.yaml")
    cost = candidate_cost(dataclasses.replace(paper_candidate(), precision="int8"))
    int8, fp32 = _stage_ms(dev.int8, cost.workloads), _stage_ms(dev, cost.workloads)
    chosen, done, picks = {}, 0, []
    for stages in cost.path_stages:
        graph = list(stages)[done:]
        done = len(stages)
        t8, t32 = sum(int8.get(s, 0) for s in graph), sum(fp32.get(s, 0) for s in graph)
        picks.append(t8 <= INT8_KEEP_RATIO * t32)
        chosen.update({s: (int8 if picks[-1] else fp32).get(s, 0.0) for s in graph})
    assert picks[0] and not all(picks)   # the encoders' graph int8, some decoder graph fp32
    want = [dev.inference_overhead_ms + sum(chosen.get(s, 0.0) + dev.stage_overhead_ms for s in stages)
            for stages in cost.path_stages]
    assert cost.path_latency_ms(dev)[1:] == pytest.approx(want)


def test_stored_workloads_recost_int8_trials_layer_by_layer():
    from explorer.study.results import compact_workloads, expand_workloads
    from explorer.cost.precision import QUANTIZABLE_KINDS, workload_quantized
    cost = candidate_cost(paper_candidate())
    compact = compact_workloads(cost)
    wl, _ = expand_workloads(json.loads(json.dumps(compact)))
    assert [workload_quantized(w) for w in wl] == [workload_quantized(w) for w in cost.workloads]
    old = {**compact, "layers": [row[:6] for row in compact["layers"]]}   # rows a study stored before
    wl_old, _ = expand_workloads(old)
    assert [w.macs for w in wl_old] == [w.macs for w in cost.workloads]
    assert [workload_quantized(w) for w in wl_old] == [workload_quantized(w) for w in cost.workloads]
    assert {w.kind for w in wl_old if workload_quantized(w)} <= set(QUANTIZABLE_KINDS)


def test_int8_quantizes_a_stage_graph_whole_with_7_bit_weights(tmp_path):
    """Every convolution (the stem, depthwise and thin ones too) gets int8 weights within 7 bits (no
    VPMADDUBSW saturation on x86 without VNNI), and the activations between them are quantized."""
    import numpy as np
    import onnx
    import torch
    from onnx import numpy_helper
    from explorer.deploy.int8_graphs import CHANNELS_LAST_UPSAMPLE_SUFFIX, quantize_graph
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 32, 3, 2, 1), torch.nn.ReLU(),
                              torch.nn.Conv2d(32, 32, 3, 1, 1, groups=32), torch.nn.ReLU(),
                              torch.nn.Conv2d(32, 48, 1), torch.nn.ReLU(), torch.nn.Conv2d(48, 16, 1), torch.nn.ReLU(),
                              torch.nn.Upsample(scale_factor=2), torch.nn.Conv2d(16, 8, 1)).eval()
    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    x = torch.rand(1, 3, 32, 32)
    torch.onnx.export(net, x, str(src), input_names=["x"], output_names=["y"], dynamo=False)
    feeds = [{"x": torch.rand(1, 3, 32, 32).numpy()} for _ in range(4)]
    assert quantize_graph(src, dst, feeds)
    g = onnx.load(str(dst)).graph
    weights = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    made_by = {o: n for n in g.node for o in n.output}
    convs = [n for n in g.node if n.op_type == "Conv"]
    assert len(convs) == 5 and all(made_by[c.input[0]].op_type == "DequantizeLinear" for c in convs)
    # the up-sampling copies the uint8 tensor (``upsamples_channels_last``)
    assert not any(n.op_type == "Resize" for n in g.node)
    copy = next(n for n in g.node if n.name.endswith(CHANNELS_LAST_UPSAMPLE_SUFFIX + "_nhwc"))
    assert made_by[copy.input[0]].op_type == "QuantizeLinear"
    for conv in convs:
        w = weights[made_by[conv.input[1]].input[0]]
        # 255 x 64 x 2 < 2**15: a pair of products cannot saturate int16
        assert w.dtype == np.int8 and np.abs(w.astype(int)).max() <= 64 and np.abs(w.astype(int)).max() >= 32


def test_int8_keeps_the_lidar_encoder_fp32_inside_a_quantized_graph(tmp_path):
    """The scan's metric depths stay float through the LiDAR encoder; the image convolutions are int8."""
    import onnx
    import torch
    from explorer.deploy.int8_graphs import quantize_graph

    class Encoders(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.image_encoder = torch.nn.Sequential(torch.nn.Conv2d(3, 16, 3, 2, 1), torch.nn.ReLU())
            self.lidar_encoder = torch.nn.Sequential(torch.nn.Conv1d(1, 16, 3, 1, 1), torch.nn.ReLU(),
                                                     torch.nn.Conv1d(16, 16, 3, 2, 1))

        def forward(self, image, scan):
            return self.image_encoder(image) + self.lidar_encoder(scan)[:, :, None, :]

    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    torch.onnx.export(Encoders().eval(), (torch.rand(1, 3, 8, 32), torch.rand(1, 1, 32)), str(src),
                      input_names=["image", "scan"], output_names=["y"], dynamo=False)
    feeds = [{"image": torch.rand(1, 3, 8, 32).numpy(), "scan": 10 * torch.rand(1, 1, 32).numpy()} for _ in range(4)]
    assert quantize_graph(src, dst, feeds)
    g = onnx.load(str(dst)).graph
    made_by = {o: n.op_type for n in g.node for o in n.output}
    convs = {n.name: n for n in g.node if n.op_type == "Conv"}
    lidar = [n for name, n in convs.items() if name.startswith("/lidar_encoder/")]
    image = [n for name, n in convs.items() if name.startswith("/image_encoder/")]
    assert len(lidar) == 2 and len(image) == 1
    assert all(made_by.get(c.input[1]) != "DequantizeLinear" for c in lidar)   # float weights
    assert made_by[image[0].input[1]] == "DequantizeLinear"


def test_int8_keeps_an_exit_heads_bilinear_products_float(tmp_path):
    """The interpolation weights of the exit's up-sampling (two matrix products) are not rounded to int8."""
    import numpy as np
    import onnx
    import torch
    from explorer.model.exits import ExitHeadConfig
    from explorer.deploy.int8_graphs import quantize_graph

    class Exit(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.exit_1 = ExitHeadConfig(in_channels=16, depth=1, width=16, upscale=4).build()

        def forward(self, x):
            return self.exit_1(x)

    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    torch.onnx.export(Exit().eval(), (torch.rand(1, 16, 8, 8),), str(src), input_names=["x"],
                      output_names=["depth"], dynamo=False)
    feeds = [{"x": torch.rand(1, 16, 8, 8).numpy()} for _ in range(4)]
    assert quantize_graph(src, dst, feeds)
    g = onnx.load(str(dst)).graph
    made_by = {o: n for n in g.node for o in n.output}
    products = [n for n in g.node if n.op_type == "MatMul"]
    assert len(products) == 2 and all("/resize/" in n.name for n in products)
    constants = {i.name for i in g.initializer} | {n.output[0] for n in g.node if n.op_type == "Constant"}
    for n in products:   # the interpolation weights reach the products as float constants, not dequantized
        assert any(i in constants or made_by[i].op_type == "Transpose" for i in n.input)
        assert not any(i in made_by and made_by[i].op_type == "DequantizeLinear" and made_by[i].input[0] in constants
                       for i in n.input)
    assert any(n.op_type == "DequantizeLinear" for n in g.node)   # the convolution is int8
    from explorer.calibration.measure import session   # the process's thread pool, as every session here
    want, got = (session(f.read_bytes()).run(None, feeds[0])[0] for f in (src, dst))
    assert np.abs(got - want).max() < 0.05 * np.abs(want).max()


def test_an_int8_section_is_fitted_from_the_fp32_profile_on_whole_int8_stage_graphs():
    """Stage graphs that run int8 in half their fp32 time give an int8 section that prices other
    candidates' graphs at half too; kinds that no int8 graph quantizes keep their fp32 price, and so do
    the body exponent and the per-stage overhead."""
    from explorer.calibration.calibrate import with_int8
    from explorer.cost.fit import MEMORY_KINDS, Observation, errors, predict_ms
    from explorer.cost.precision import workload_quantized
    fp32 = get_device("tx2")

    def halved(cands) -> list:
        obs = []
        for c in cands:
            cost = candidate_cost(c, (224, 224))
            for stage in sorted({w.stage for w in cost.workloads}):
                wl = [w for w in cost.workloads if w.stage == stage]
                ms = 0.5 * predict_ms(fp32, Observation(stage, wl, 1.0, stages=1))
                obs.append(Observation(f"{c.key}/{stage}", wl, ms, weight=4.0, stages=1))
        return obs
    cands = SearchSpace.from_yaml("anytime_depth").random_candidates(8, 0)
    fitted_on, held_out = halved(cands[:5]), halved(cands[5:])
    layers = [(w, 0.5 * fp32.layer_ms(w)) for o in fitted_on for w in o.workloads if workload_quantized(w)]
    prof = with_int8(fp32, [], layers, fitted_on)
    assert prof.precisions == ("fp32", "int8")
    assert errors(prof.int8, held_out)["error"].abs().median() < 0.05
    assert errors(fp32, held_out)["error"].median() > 0.8   # fp32 prices them at twice that
    unquantized = set(fp32.kinds) - {w.kind for w, _ in layers} - set(MEMORY_KINDS)
    assert unquantized and all(prof.int8.kinds[k] == fp32.kinds[k] for k in unquantized)
    assert (prof.int8.body_exponent, prof.int8.stage_overhead_ms) == (fp32.body_exponent, fp32.stage_overhead_ms)


def test_an_int8_graph_prices_its_lidar_encoder_at_fp32(tmp_path):
    from explorer.cost.devices import _stage_ms
    dev = get_device(_with_int8(tmp_path, slower=0.25))   # every int8 layer 4x as fast
    cost = candidate_cost(dataclasses.replace(paper_candidate(), precision="int8"))
    int8, fp32 = _stage_ms(dev.int8, cost.workloads), _stage_ms(dev, cost.workloads)
    assert int8["lidar_encoder"] < fp32["lidar_encoder"]
    encoders = cost.path_stages[0]   # path 1's stages (index 0 of the latencies is the scan)
    want = dev.inference_overhead_ms + sum((fp32 if s == "lidar_encoder" else int8)[s] + dev.stage_overhead_ms
                                           for s in encoders)
    assert cost.path_latency_ms(dev)[1] == pytest.approx(want)


def test_int8_quantizes_a_graph_whose_tensor_barely_varies(tmp_path):
    """An untrained exit head gives 2.5 m +- 1e-5 everywhere: too narrow for the percentile
    calibrator's 2048-bin histogram (numpy refuses it); min / max ranges take that graph."""
    import onnx
    import torch
    from explorer.deploy.int8_graphs import quantize_graph
    conv = torch.nn.Conv2d(4, 1, 1)
    with torch.no_grad():
        conv.weight.mul_(1e-5)
        conv.bias.fill_(2.5)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 1), conv).eval()
    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    torch.onnx.export(net, torch.rand(1, 3, 64, 64), str(src), input_names=["x"], output_names=["y"], dynamo=False)
    assert quantize_graph(src, dst, [{"x": torch.rand(1, 3, 64, 64).numpy()} for _ in range(2)])
    assert "QuantizeLinear" in {n.op_type for n in onnx.load(str(dst)).graph.node}


def test_quantizing_in_process_prints_nothing(tmp_path):
    """onnxruntime's calibrator prints five lines per graph; a calibration bundle quantizes a hundred."""
    import subprocess
    import sys

    import onnx
    import torch
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(4, 1, 1)).eval()
    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    torch.onnx.export(net, torch.rand(1, 3, 32, 32), str(src), input_names=["x"], output_names=["y"], dynamo=False)
    # a process of its own: this one's sessions share onnxruntime's global thread pool, which the
    # quantizer's own sessions may not join (the export sends them to a worker process for that)
    script = ("import sys, numpy as np; from pathlib import Path; from explorer.deploy.int8_graphs import _quantize; "
              "feeds = [{'x': np.random.rand(1, 3, 32, 32).astype(np.float32)} for _ in range(2)]; "
              "sys.exit(0 if _quantize(Path(sys.argv[1]), Path(sys.argv[2]), feeds) else 1)")
    done = subprocess.run([sys.executable, "-c", script, str(src), str(dst)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout == ""
    assert "QuantizeLinear" in {n.op_type for n in onnx.load(str(dst)).graph.node}


def test_a_graph_without_convolutions_stays_fp32(tmp_path):
    import torch
    from explorer.deploy.int8_graphs import quantize_graph
    src, dst = tmp_path / "f.onnx", tmp_path / "q.onnx"
    torch.onnx.export(torch.nn.ReLU(), torch.rand(1, 4), str(src), input_names=["x"], output_names=["y"],
                      dynamo=False)
    assert not quantize_graph(src, dst, [{"x": torch.rand(1, 4).numpy()}])
    assert dst.read_bytes() == src.read_bytes()


def _quantized_decoder(tmp_path, skip_channels: int):
    """A decoder stage (32 -> 16 channels, skip of ``skip_channels``) quantized: (its graph, inputs)."""
    import torch
    from explorer.model.decoder import DecoderStageConfig
    from explorer.deploy.int8_graphs import quantize_graph
    torch.manual_seed(0)   # the same weights, inputs and calibration frames on every call
    net = DecoderStageConfig(32, 16, has_skip=True).build().eval()
    src, dst = tmp_path / "f.onnx", tmp_path / f"q{skip_channels}.onnx"
    x, skip = torch.rand(1, 32, 14, 14), torch.rand(1, skip_channels, 28, 28)
    torch.onnx.export(net, (x, skip), str(src), input_names=["x", "skip"], output_names=["y"], dynamo=False)
    feeds = [{"x": torch.rand(1, 32, 14, 14).numpy(), "skip": torch.rand(1, skip_channels, 28, 28).numpy()}
             for _ in range(4)]
    assert quantize_graph(src, dst, feeds)
    return dst, {"x": x.numpy(), "skip": skip.numpy()}, net(x, skip).detach().numpy()


@pytest.mark.parametrize("skip_channels", [8, 16, 24])   # padded, as it is, sliced
def test_a_quantized_decoder_up_samples_and_adds_its_skip_channels_last(tmp_path, monkeypatch, skip_channels):
    """onnxruntime runs the quantized convolutions channels-last; the decoder's nearest up-sampling is
    copied on the uint8 tensor channels-last (``upsamples_channels_last``) and its skip added so
    (``probe_script.channels_last_skip_adds``): the optimised graph transposes only where tensors enter
    and leave it, and computes exactly what onnxruntime's channels-first Resize and addition computed."""
    import numpy as np
    import onnx
    from explorer import probe as probe_script
    from explorer.calibration.measure import session
    dst, feed, ref = _quantized_decoder(tmp_path, skip_channels)
    assert not any(n.op_type == "Resize" for n in onnx.load(str(dst)).graph.node)
    session(dst.read_bytes(), save_optimized=tmp_path / "opt.onnx")
    graph = onnx.load(str(tmp_path / "opt.onnx")).graph
    made_by = {o: n for n in graph.node for o in n.output}
    perm = lambda n: list(onnx.helper.get_attribute_value(n.attribute[0]))  # noqa: E731
    transposes = sorted((perm(n), made_by[n.input[0]].op_type) for n in graph.node if n.op_type == "Transpose")
    # x and the skip channels-last once quantized, the sum channels-first to leave: nothing in between
    assert transposes == [([0, 2, 3, 1], "QuantizeLinear")] * 2 + [([0, 3, 1, 2], "QLinearAdd")]
    add = next(n for n in graph.node if n.op_type == "QLinearAdd")
    assert all(made_by[add.input[k]].op_type != "Transpose" or perm(made_by[add.input[k]]) == [0, 2, 3, 1]
               for k in (0, 3))
    q8 = session(dst.read_bytes()).run(None, feed)[0]
    assert np.abs(q8 - ref).max() < 0.05 * np.abs(ref).max()

    # onnxruntime's own channels-first addition: the same numbers
    monkeypatch.setattr(probe_script.sessions, "channels_last_skip_adds", lambda model: 0)
    np.testing.assert_array_equal(session(dst.read_bytes()).run(None, feed)[0], q8)


@pytest.mark.parametrize("factor,mode,rewritten", [(2, "nearest", True), (3, "nearest", True), (2, "linear", False)])
def test_a_uint8_nearest_upsampling_is_copied_channels_last_with_the_same_values(factor, mode, rewritten):
    """DequantizeLinear, nearest Resize by an integer factor, QuantizeLinear of the same scale: the same
    uint8 values as the copy ``upsamples_channels_last`` makes; a bilinear one is left as it is."""
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper
    from explorer.calibration.measure import session
    from explorer.deploy.int8_graphs import upsamples_channels_last
    const = lambda name, v: numpy_helper.from_array(np.array(v), name)  # noqa: E731
    nodes = [helper.make_node("DequantizeLinear", ["a", "s", "z"], ["af"]),
             helper.make_node("Resize", ["af", "", "scales"], ["rf"], mode=mode,
                              coordinate_transformation_mode="asymmetric",
                              **({"nearest_mode": "floor"} if mode == "nearest" else {})),
             helper.make_node("QuantizeLinear", ["rf", "s", "z"], ["y"])]
    graph = helper.make_graph(
        nodes, "up", [helper.make_tensor_value_info("a", TensorProto.UINT8, [1, 5, 3, 4])],
        [helper.make_tensor_value_info("y", TensorProto.UINT8, [1, 5, 3 * factor, 4 * factor])],
        [const("s", np.float32(0.1)), const("z", np.uint8(7)),
         const("scales", np.array([1, 1, factor, factor], np.float32))])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    before = model.SerializeToString()
    assert upsamples_channels_last(model) == int(rewritten)
    assert any(n.op_type == "Resize" for n in model.graph.node) != rewritten
    a = np.random.default_rng(0).integers(0, 256, (1, 5, 3, 4), dtype=np.uint8)
    expected = session(before).run(None, {"a": a})[0]
    if rewritten:
        np.testing.assert_array_equal(expected, a.repeat(factor, axis=2).repeat(factor, axis=3))
    np.testing.assert_array_equal(session(model.SerializeToString()).run(None, {"a": a})[0], expected)


def test_a_zero_pad_between_quantize_nodes_pads_uint8():
    """The decoder's widening of a narrower skip (a zero Pad) runs on the uint8 tensor, padded with its
    zero point, instead of dequantized, padded in float and quantized again; same values either way."""
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper
    from explorer.calibration.measure import session
    from explorer.deploy.int8_graphs import pads_kept_uint8
    const = lambda name, v: numpy_helper.from_array(np.array(v), name)  # noqa: E731

    def model(scale_after: str):
        nodes = [helper.make_node("QuantizeLinear", ["x", "s", "z"], ["xq"]),
                 helper.make_node("DequantizeLinear", ["xq", "s", "z"], ["xf"]),
                 helper.make_node("Pad", ["xf", "pads"], ["p"], mode="constant"),
                 helper.make_node("QuantizeLinear", ["p", scale_after, "z"], ["pq"]),
                 helper.make_node("DequantizeLinear", ["pq", scale_after, "z"], ["y"])]
        graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2, 3, 3])],
                                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
                                  [const("s", np.float32(0.05)), const("s2", np.float32(0.1)),
                                   const("z", np.uint8(7)), const("pads", np.array([0, 0, 0, 0, 0, 4, 0, 0]))])
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])

    x = {"x": np.random.default_rng(0).uniform(-0.3, 1.0, (1, 2, 3, 3)).astype(np.float32)}
    padded = model("s")
    before = session(padded.SerializeToString()).run(None, x)[0]
    assert pads_kept_uint8(padded) == 1
    assert [n.op_type for n in padded.graph.node] == ["QuantizeLinear", "Pad", "DequantizeLinear"]
    pad = padded.graph.node[1]
    assert pad.input[0] == "xq" and numpy_helper.to_array(
        next(i for i in padded.graph.initializer if i.name == pad.input[2])) == 7
    after = session(padded.SerializeToString()).run(None, x)[0]
    assert after.shape == (1, 6, 3, 3) and not after[:, 2:].any()
    np.testing.assert_array_equal(before, after)
    other = model("s2")   # the padded tensor quantized with another scale: left alone
    kept = other.SerializeToString()
    assert pads_kept_uint8(other) == 0 and other.SerializeToString() == kept
