import dataclasses

import numpy as np
import pytest
import yaml

from explorer.cost import candidate_cost, get_device
from explorer.cost.devices import DeviceProfile, KindCost, available_devices
from explorer.cost.workloads import KINDS, Workload
from explorer.errors import UserError
from explorer.space import paper_candidate


def _profile(overlap):
    return DeviceProfile("hand", "", overlap, bandwidth_gbs=1.0,
                         kinds={k: KindCost(gmacs=2.0, overhead_ms=0.5) for k in KINDS},
                         inference_overhead_ms=1.0, stage_overhead_ms=0.25,
                         energy_fixed_j=0.1, active_power_w=10.0)


@pytest.mark.parametrize("overlap,exponent,weight_traffic", [(False, 1.0, True), (True, 1.0, True),
                                                             (False, 1.15, False), (True, 0.95, False)])
def test_a_batch_of_observations_is_priced_as_each_one_alone(overlap, exponent, weight_traffic):
    from explorer.cost.fit import Observation, ObservationBatch, errors, predict_ms
    rng = np.random.default_rng(0)
    kinds = {k: KindCost(gmacs=float(rng.uniform(1, 50)), overhead_ms=float(rng.uniform(0, 0.1)),
                         bandwidth_gbs=None if i % 2 else float(rng.uniform(2, 20)),
                         weight_traffic=weight_traffic or i % 3 == 0) for i, k in enumerate(KINDS)}
    prof = dataclasses.replace(get_device("rpi4"), overlap=overlap, body_exponent=exponent, kinds=kinds,
                               stage_overhead_ms=0.07, inference_overhead_ms=0.4)
    cost = candidate_cost(paper_candidate(), (96, 128))
    obs = [Observation(f"{i}", cost.workloads[i:i + n], 1.0 + i, stages=i % 3, end_to_end=i % 2 == 0)
           for i, n in ((0, 1), (3, 7), (10, 0), (5, len(cost.workloads) - 5), (40, 2))]
    alone = [predict_ms(prof, o) for o in obs]
    assert ObservationBatch(obs).predict_ms(prof) == pytest.approx(alone, rel=1e-12)
    assert errors(prof, obs)["predicted_ms"].tolist() == pytest.approx(alone, rel=1e-12)
    assert alone[2] == pytest.approx(0.07 + 0.4)   # no workloads (one stage, end to end): its overheads alone


def test_cost_arithmetic_on_hand_workloads():
    w = Workload("s", "l", "pointwise", (1,), (1,), 1, 1, macs=4_000_000, params=0,
                 bytes_read=1_000_000, bytes_written=1_000_000)
    # compute 4e6 / 2e9 s = 2 ms; memory 2e6 B / 1e9 B/s = 2 ms... make them differ:
    w2 = dataclasses.replace(w, bytes_written=3_000_000)  # memory 4 ms
    assert _profile(True).layer_ms(w2) == pytest.approx(0.5 + 4.0)       # overlap: the longer
    assert _profile(False).layer_ms(w2) == pytest.approx(0.5 + 2.0 + 4.0)  # CPU: the sum
    assert _profile(True).energy_j(10.0) == pytest.approx(0.1 + 10.0 * 0.01)
    assert _profile(True).energy_j(0.0) == 0.0


def test_path_latency_includes_overheads():
    prof = _profile(False)
    cost = candidate_cost(paper_candidate())
    ms = cost.path_latency_ms(prof)
    per = {}
    for w in cost.workloads:
        per[w.stage] = per.get(w.stage, 0) + prof.layer_ms(w)
    expected_p1 = 1.0 + sum(per[s] + 0.25 for s in cost.path_stages[0])
    assert ms[1] == pytest.approx(expected_p1)


def test_all_builtins_load_and_round_trip(tmp_path):
    assert {"tx2", "tx2-cpu", "rpi4", "jetson-nano", "orin-nano", "rpi5"} <= set(available_devices())
    for name in available_devices():
        p = get_device(name)
        f = tmp_path / f"{name}.yaml"
        f.write_text(p.to_yaml())
        q = get_device(str(f))
        assert q.kinds == p.kinds and q.energy_fixed_j == pytest.approx(p.energy_fixed_j)
        assert "sources" in p.provenance
    assert not get_device("orin-nano").calibrated and get_device("tx2").calibrated


def test_profile_errors(tmp_path):
    with pytest.raises(UserError, match="unknown device"):
        get_device("tx3")
    with pytest.raises(UserError, match="no such file"):
        get_device(str(tmp_path / "none.yaml"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\noverlap: true\nbandwidth_gbs: 10\nkinds: {conv: {gmacs: 1}}\n")
    with pytest.raises(UserError, match="lacks"):
        get_device(str(bad))
    bad.write_text(": : :")
    with pytest.raises(UserError, match="YAML"):
        get_device(str(bad))
    data = get_device("tx2").to_dict()
    data["kinds"]["conv"]["gmacs"] = -1
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match="positive"):
        get_device(str(bad))


def test_tx2_reproduces_its_calibration(shared_data):
    from explorer.cost.fit import PAPER_TX2_PATHS_MS, Observation, errors, kernel_workloads
    tx2 = get_device("tx2")
    obs = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(shared_data / "tx2-tvm-kernels" / "kernels.csv", "gpu")]
    assert len(obs) == 71
    assert errors(tx2, obs)["error"].abs().median() <= 0.20
    ms = candidate_cost(paper_candidate(), paper_graph=True).path_latency_ms(tx2)[1:]
    for got, want in zip(ms, PAPER_TX2_PATHS_MS):
        assert abs(got / want - 1) <= 0.10
    # this project's graph leaves the last up-sampling to the exit head: the same values, less work
    assert candidate_cost(paper_candidate()).path_latency_ms(tx2)[-1] < ms[-1]
    cpu = get_device("tx2-cpu")
    obs = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(shared_data / "tx2-tvm-kernels" / "kernels.csv", "cpu")]
    assert errors(cpu, obs)["error"].abs().median() <= 0.20


def test_tx2_energy_model_matches_paper_points():
    tx2 = get_device("tx2")
    assert tx2.energy_j(6.37) == pytest.approx(0.2, abs=1e-3)
    assert tx2.energy_j(554.7) == pytest.approx(6.244, abs=1e-3)


def test_rpi4_reproduces_table2():
    from explorer.cost.fit import PAPER_RPI4_TABLE2, rpi4_table2
    got = rpi4_table2(get_device("rpi4"))
    for spec, want in PAPER_RPI4_TABLE2.items():
        assert abs(got[spec] - want) <= 0.03, spec


def test_one_channel_pointwise_layers_have_their_own_kind(tmp_path):
    from explorer.calibration.calibrate import fit_host
    from explorer.calibration.sweep import HOST_KINDS, SweepLayer, layer_graph
    cost = candidate_cost(paper_candidate())
    heads = [w for w in cost.workloads if w.kind == "pointwise_1ch"]
    # every exit head ends in a 1x1 convolution to depth, and nothing else is one
    assert {w.stage for w in heads} == {s for s in {w.stage for w in cost.workloads} if s.startswith("exit")}
    assert all(w.out_shape[0] == 1 and w.kernel == 1 for w in heads)
    assert not any(w.kind == "pointwise" and w.out_shape[0] == 1 for w in cost.workloads)
    # a profile written before the kind existed prices it as pointwise
    data = get_device("tx2").to_dict()
    del data["kinds"]["pointwise_1ch"]
    f = tmp_path / "old.yaml"
    f.write_text(yaml.safe_dump(data))
    assert get_device(str(f)).kinds["pointwise_1ch"] == get_device(str(f)).kinds["pointwise"]
    # the host fit tells the kinds apart: layers timed as a device with one-channel layers 3x slower
    truth = DeviceProfile("truth", "", False, 10.0, {k: KindCost(20.0, 0.01) for k in HOST_KINDS},
                          stage_overhead_ms=0.02)
    truth = dataclasses.replace(truth, kinds={**truth.kinds, "pointwise_1ch": KindCost(20.0 / 3, 0.01, 10.0 / 3)})
    layers = [SweepLayer("pointwise", (c, s, s), o) for c in (16, 64, 256) for s in (14, 56, 112) for o in (16, 128)]
    layers += [SweepLayer("pointwise_1ch", (c, s, s), 1) for c in (8, 16, 32, 64) for s in (28, 112, 224)]
    layers += [SweepLayer(k, (32, 28, 28), 32, 3, 1) for k in ("depthwise", "conv")]
    layers += [SweepLayer("conv1d", (16, 224), 16, 3, 1), SweepLayer("resize", (16, 28, 28), 16, 0, 2),
               SweepLayer("add", (16, 28, 28), 16), SweepLayer("concat", (16, 28), 0, extra=16),
               SweepLayer("slice", (16, 28, 28), 16, extra=3)]
    measured = [(wl, truth.layer_ms(wl) + truth.stage_overhead_ms) for wl in (layer_graph(layer)[2] for layer in layers)]
    fitted = fit_host(measured)
    for wl, ms in measured:
        if wl.kind.startswith("pointwise"):
            assert fitted.layer_ms(wl) + fitted.stage_overhead_ms == pytest.approx(ms, rel=0.10), wl.layer


def test_the_exits_bilinear_products_have_their_own_kind(tmp_path):
    from explorer.calibration.calibrate import fit_host
    from explorer.calibration.sweep import HOST_KINDS, SweepLayer, layer_graph
    from explorer.calibration.measure import session
    import torch
    from explorer.model.ops import Resize
    cost, paper = candidate_cost(paper_candidate()), candidate_cost(paper_candidate(), paper_graph=True)
    products = [w for w in cost.workloads if w.kind == "bilinear"]
    assert {w.stage for w in products} == {"exit_0", "exit_1", "exit_2"}   # exit 4 up-samples nearest, x2
    assert not any(w.kind == "bilinear" for w in paper.workloads)   # the paper's graph: Resize operators
    exit_2 = next(w for w in products if w.stage == "exit_2")   # 56x56 -> 224x224: rows, then columns
    assert exit_2.in_shape == (1, 56, 56) and exit_2.macs == 224 * 56 * 56 + 224 * 56 * 224 and exit_2.params == 0
    # the calibration times them as the model exports them
    graph, feeds, wl = layer_graph(SweepLayer("bilinear", (1, 7, 14), 1, 0, 8))
    np.testing.assert_allclose(session(graph).run(None, feeds)[0],
                               Resize(8, "bilinear")(torch.from_numpy(feeds["x"])).numpy(), rtol=1e-6, atol=1e-6)
    assert (wl.kind, wl.out_shape) == ("bilinear", (1, 56, 112))
    # a profile written before the kind existed prices them as pointwise layers
    data = get_device("tx2").to_dict()
    data["kinds"].pop("bilinear", None)
    f = tmp_path / "old.yaml"
    f.write_text(yaml.safe_dump(data))
    assert get_device(str(f)).kinds["bilinear"] == get_device(str(f)).kinds["pointwise"]
    # the host fit tells them apart: a device where they run at a quarter of the pointwise rate
    truth = DeviceProfile("truth", "", False, 10.0, {k: KindCost(20.0, 0.01) for k in HOST_KINDS},
                          stage_overhead_ms=0.02)
    truth = dataclasses.replace(truth, kinds={**truth.kinds, "bilinear": KindCost(5.0, 0.01)})
    layers = [SweepLayer("pointwise", (c, s, s), o) for c in (16, 64, 256) for s in (14, 56, 112) for o in (16, 128)]
    layers += [SweepLayer("bilinear", (1, s, s), 1, 0, f) for s in (7, 14, 28) for f in (2, 4, 8)]
    layers += [SweepLayer(k, (32, 28, 28), 32, 3, 1) for k in ("depthwise", "conv")]
    layers += [SweepLayer("pointwise_1ch", (16, 56, 56), 1), SweepLayer("conv1d", (16, 224), 16, 3, 1),
               SweepLayer("resize", (16, 28, 28), 16, 0, 2), SweepLayer("add", (16, 28, 28), 16),
               SweepLayer("concat", (16, 28), 0, extra=16), SweepLayer("slice", (16, 28, 28), 16, extra=3)]
    measured = [(wl, truth.layer_ms(wl) + truth.stage_overhead_ms) for wl in (layer_graph(layer)[2] for layer in layers)]
    fitted = fit_host(measured)
    for wl, ms in measured:
        if wl.kind == "bilinear":
            assert fitted.layer_ms(wl) + fitted.stage_overhead_ms == pytest.approx(ms, rel=0.10), wl.layer


def test_body_exponent_prices_and_round_trips(tmp_path):
    w = Workload("s", "l", "pointwise", (1,), (1,), 1, 1, macs=4_000_000, params=0,
                 bytes_read=1_000_000, bytes_written=3_000_000)
    steep = dataclasses.replace(_profile(True), body_exponent=1.2)
    assert steep.layer_ms(w) == pytest.approx(0.5 + 4.0 ** 1.2)
    f = tmp_path / "steep.yaml"
    f.write_text(steep.to_yaml())
    assert get_device(str(f)).body_exponent == 1.2 and "body_exponent" not in _profile(True).to_dict()
    data = steep.to_dict()
    data["body_exponent"] = -1
    f.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match="body_exponent"):
        get_device(str(f))


def test_host_fit_finds_the_body_exponent_from_stage_graphs_at_several_sizes():
    from explorer.calibration.calibrate import fit_host
    from explorer.calibration.sweep import HOST_KINDS, SweepLayer, layer_graph
    from explorer.cost.fit import Observation
    from explorer.space import SearchSpace
    truth = DeviceProfile("truth", "", False, 8.0, {k: KindCost(30.0, 0.02) for k in HOST_KINDS},
                          stage_overhead_ms=0.03, body_exponent=1.15)
    layers = [SweepLayer(k, (c, s, s), c, 3 if k in ("depthwise", "conv") else 1, 1)
              for k in ("pointwise", "depthwise", "conv") for c in (16, 64) for s in (14, 56)]
    layers += [SweepLayer("pointwise_1ch", (16, 56, 56), 1), SweepLayer("conv1d", (16, 224), 16, 3, 1),
               SweepLayer("resize", (16, 28, 28), 16, 0, 2), SweepLayer("add", (16, 28, 28), 16),
               SweepLayer("concat", (16, 28), 0, extra=16), SweepLayer("slice", (16, 28, 28), 16, extra=3)]
    measured = [(wl, truth.layer_ms(wl) + truth.stage_overhead_ms) for wl in (layer_graph(layer)[2] for layer in layers)]
    stage_obs = []
    for i, cand in enumerate(SearchSpace.from_yaml("anytime_depth").random_candidates(6, 3)):
        for size in ((224, 224), (224, 320), (192, 640)):
            cost = candidate_cost(cand, size)
            for stage in cost.path_stages[-1]:
                wl = [w for w in cost.workloads if w.stage == stage]
                ms = sum(truth.layer_ms(w) for w in wl) + truth.stage_overhead_ms
                stage_obs.append(Observation(f"{i}/{stage}", wl, ms, weight=4.0, stages=1, group=f"{size}"))
    fitted = fit_host(measured, stage_obs=stage_obs)
    assert fitted.body_exponent > 1.0
    flat = fit_host(measured, stage_obs=[dataclasses.replace(o, group="one size") for o in stage_obs])
    assert flat.body_exponent == 1.0   # one size cannot tell an exponent from rates


def test_a_candidate_timer_times_its_paths_again_with_the_same_sessions():
    import math
    from explorer.calibration.measure import CandidateTimer
    from explorer.model import build_network
    cand = paper_candidate()
    net = build_network(cand)
    timer = CandidateTimer(net, (32, 64))
    first, again = timer.measure(repeats=2, warmup=1), timer.measure(repeats=2, warmup=1)
    for m in (first, again):
        assert len(m.path_ms) == cand.num_paths and m.input_size == (32, 64)
        assert list(m.stage_ms) == [spec.name for spec in net.specs]
        # a path is ready when the stages up to its exit are done: cumulative stage times
        ends = [k for k, spec in enumerate(net.specs) if spec.path is not None]
        assert m.path_ms[1:] == pytest.approx([sum(list(m.stage_ms.values())[:k + 1]) for k in ends])
        assert m.whole_ms > 0 and all(ms > 0 for ms in m.stage_ms.values())
    assert math.isnan(CandidateTimer(net, (32, 64), whole=False).measure(repeats=1, warmup=0).whole_ms)
