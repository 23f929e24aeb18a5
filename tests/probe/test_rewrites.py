"""The graph rewrites the probe and the runtime share (explorer.probe.rewrites) and the chains of
sessions that time and run stage graphs handing tensors over as onnxruntime holds them
(explorer.probe.timing)."""

import platform

import numpy as np
import pytest

from explorer import probe


def _skip_add_model(start: int, end: int, skip_channels: int = 32):
    """x -> 1x1 conv (16 channels) + skip[:, start:end] -> 1x1 conv: the decoder's skip addition."""
    from onnx import TensorProto, helper, numpy_helper
    rng = np.random.default_rng(0)
    inits = [numpy_helper.from_array(rng.standard_normal((16, 16, 1, 1)).astype(np.float32), "w1"),
             numpy_helper.from_array(rng.standard_normal((16, 16, 1, 1)).astype(np.float32), "w2"),
             numpy_helper.from_array(np.array([start], np.int64), "starts"),
             numpy_helper.from_array(np.array([end], np.int64), "ends"),
             numpy_helper.from_array(np.array([1], np.int64), "axes")]
    nodes = [helper.make_node("Conv", ["x", "w1"], ["u"]),
             helper.make_node("Slice", ["skip", "starts", "ends", "axes"], ["fit"]),
             helper.make_node("Add", ["u", "fit"], ["sum"]),
             helper.make_node("Conv", ["sum", "w2"], ["y"])]
    vi = lambda n, c: helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, c, 8, 8])  # noqa: E731
    graph = helper.make_graph(nodes, "skip", [vi("x", 16), vi("skip", skip_channels)], [vi("y", 16)], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="onnxruntime blocks channels on x86")
def test_skip_additions_stay_blocked_only_where_the_slice_keeps_whole_leading_blocks(tmp_path):
    import onnx
    from explorer.probe import session
    rng = np.random.default_rng(1)
    feeds = {"x": rng.standard_normal((1, 16, 8, 8), dtype=np.float32),
             "skip": rng.standard_normal((1, 32, 8, 8), dtype=np.float32)}
    for start, end, rewritten in ((0, 16, True), (8, 24, False)):
        model = _skip_add_model(start, end)
        plain = session(model, blocked_skips=False, save_optimized=tmp_path / "plain.onnx")
        blocked = session(model, save_optimized=tmp_path / "blocked.onnx")
        reorders = [[n.op_type for n in onnx.load(str(tmp_path / f)).graph.node].count("ReorderOutput")
                    for f in ("plain.onnx", "blocked.onnx")]
        # rewritten, the sum is never converted back to NCHW: only y is (the skip, a graph input, is
        # converted to the blocked layout instead of the sum)
        assert reorders == ([2, 1] if rewritten else [2, 2])
        np.testing.assert_array_equal(blocked.run(None, feeds)[0], plain.run(None, feeds)[0])


def _depth_maps(sessions: list, size: tuple[int, int]) -> list[np.ndarray]:
    """Every depth map that stage ``sessions``, run in order on the example inputs, output."""
    from explorer.model.onnx import example_inputs
    env = {k: v.numpy() for k, v in example_inputs(size).items()}
    for s in sessions:
        outs = [o.name for o in s.get_outputs()]
        env.update(zip(outs, s.run(outs, {i.name: env[i.name] for i in s.get_inputs()})))
    return [env[k] for k in sorted(env) if k.startswith("depth_")]


def test_chain_sessions_hand_tensors_over_blocked_with_the_same_results():
    """The probe and the held-out timings run a candidate's stage graphs as the runtime does: tensors
    pass from one to the next in onnxruntime's blocked layout where both sides hold them so."""
    import torch
    from explorer.model import build_network
    from explorer.model.onnx import export_stages
    from explorer.space import paper_candidate
    torch.manual_seed(0)
    graphs = [model for _, model in export_stages(build_network(paper_candidate()).eval(), (64, 64))]
    chained, plain = probe.chain_sessions(graphs), [probe.session(m) for m in graphs]
    names = {n.name for s in chained for n in s.get_inputs()}
    if platform.machine() in ("x86_64", "AMD64"):   # onnxruntime blocks channels on x86
        assert any(n.endswith(probe.SUFFIX) for n in names)
    results = [_depth_maps(sessions, (64, 64)) for sessions in (chained, plain)]
    assert len(results[0]) == paper_candidate().num_paths
    for a, b in zip(*results):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_time_chain_runs_the_graphs_in_order_round_after_round():
    calls = []
    fns = [lambda k=k: calls.append(k) for k in range(3)]
    got = probe.time_chain(fns, warmup=1, repeats=2, timed=[True, False, True], new_round=lambda: calls.append("new"))
    assert calls == ["new", 0, 1, 2] * 3   # one untimed round, then two timed ones
    assert got[1] is None and all(isinstance(ms, float) and ms >= 0 for ms in (got[0], got[2]))


def _transposed_pair(reader_extra=False):
    """A producer that outputs x by transposing a channels-last tensor channels-first, and a reader that
    transposes x channels-last again (and, ``reader_extra``, also reads it as it is)."""
    from onnx import TensorProto, helper
    producer = helper.make_graph(
        [helper.make_node("Identity", ["a"], ["h"]), helper.make_node("Transpose", ["h"], ["x"], perm=[0, 3, 1, 2])],
        "p", [helper.make_tensor_value_info("a", TensorProto.UINT8, None)],
        [helper.make_tensor_value_info("x", TensorProto.UINT8, None)])
    nodes = [helper.make_node("Transpose", ["x"], ["t"], perm=[0, 2, 3, 1]),
             helper.make_node("Identity", ["t"], ["out"])]
    if reader_extra:
        nodes.append(helper.make_node("Identity", ["x"], ["extra"]))
    reader = helper.make_graph(nodes, "r", [helper.make_tensor_value_info("x", TensorProto.UINT8, None)],
                               [helper.make_tensor_value_info(n, TensorProto.UINT8, None)
                                for n in ["out"] + ["extra"] * reader_extra])
    return helper.make_model(producer), helper.make_model(reader)


def test_tensors_made_and_read_channels_last_are_handed_over_so():
    from onnx import TensorProto
    producer, reader = _transposed_pair()
    assert probe.hand_off_channels_last([producer, reader], [["a"], ["x"]], [["x"], ["out"]]) == ["x"]
    handed = "x" + probe.NHWC_SUFFIX
    assert [(o.name, o.type.tensor_type.elem_type) for o in producer.graph.output] == [(handed, TensorProto.UINT8)]
    assert [n.op_type for n in producer.graph.node] == ["Identity"]   # neither transpose is left
    assert [i.name for i in reader.graph.input] == [handed]
    assert [(n.op_type, list(n.input)) for n in reader.graph.node] == [("Identity", [handed])]

    producer, reader = _transposed_pair(reader_extra=True)   # also read channels-first: left as it is
    before = (producer.SerializeToString(), reader.SerializeToString())
    assert probe.hand_off_channels_last([producer, reader], [["a"], ["x"]], [["x"], ["out", "extra"]]) == []
    assert (producer.SerializeToString(), reader.SerializeToString()) == before


def test_chain_sessions_hand_the_bundles_int8_graphs_uint8_channels_last_with_the_same_results():
    """Between int8 graphs the runtime hands uint8 tensors channels-last; the probe times the bundle's
    int8 graphs so too."""
    import torch
    from explorer.calibration.bundle import _int8_graphs
    from explorer.model import build_network
    from explorer.space import paper_candidate
    torch.manual_seed(0)
    graphs = [model for _, model in _int8_graphs(build_network(paper_candidate()).eval(), (64, 64))]
    chained, plain = probe.chain_sessions(graphs), [probe.session(m) for m in graphs]
    names = {n.name for s in chained for n in s.get_inputs()}
    if platform.machine() in ("x86_64", "AMD64"):   # onnxruntime runs quantized convolutions channels-last there
        assert any(n.endswith(probe.NHWC_SUFFIX) for n in names)
    results = [_depth_maps(sessions, (64, 64)) for sessions in (chained, plain)]
    assert len(results[0]) == paper_candidate().num_paths - 1   # path 0's graph is not quantized
    for a, b in zip(*results):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
