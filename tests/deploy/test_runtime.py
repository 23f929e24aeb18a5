import gc
import platform
import time

import numpy as np
import pytest
import torch

from explorer.probe import SUFFIX, UINT8_NHWC_SUFFIX, UINT8_SUFFIX, hand_off_blocked, hand_off_quantized
from explorer.deploy.export import export_network
from explorer.model import build_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.space import paper_candidate

SIZE = (64, 96)


@pytest.fixture(scope="module")
def paper_export(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    torch.manual_seed(0)
    export_network(build_network(paper_candidate()), out, SIZE, devices=())
    return out


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((3, *SIZE), dtype=np.float32), rng.uniform(0.5, 8.0, SIZE[1]).astype(np.float32)


def test_blocked_handoff_gives_the_same_maps(paper_export):
    blocked, plain = AnytimeRunner(paper_export), AnytimeRunner(paper_export, handoff=False)
    assert plain.handed_off == {}
    if platform.machine() in ("x86_64", "AMD64"):   # onnxruntime blocks channels on x86 (AVX2 and up)
        # the decoder's running feature map, read by the next decoder (x0, x1, x2), and the encoder's skips,
        # which each decoder adds blocked (``probe_script.blocked_skip_adds``)
        assert blocked.handed_off == dict.fromkeys(["x0", "skip_s8", "x1", "skip_s4", "x2", "skip_s2"], "blocked")
        assert any(n.endswith(SUFFIX) for _, _, ins, _ in blocked.sessions for n in ins)
    for seed in range(2):
        img, scan = _inputs(seed)
        for a, b in zip(blocked.depths(img, scan), plain.depths(img, scan)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        assert np.allclose(blocked.run(img, scan).depth, plain.run(img, scan).depth, rtol=1e-5, atol=1e-6)


def _reorder_model(inputs, outputs, nodes):
    from onnx import TensorProto, helper
    vi = lambda n: helper.make_tensor_value_info(n, TensorProto.FLOAT, None)  # noqa: E731
    return helper.make_model(helper.make_graph(nodes, "g", [vi(n) for n in inputs], [vi(n) for n in outputs]))


def test_hand_off_rewrites_only_tensors_every_reader_blocks():
    from onnx import helper
    reorder = lambda i, o: helper.make_node("ReorderInput", [i], [o], domain="com.microsoft.nchwc",  # noqa: E731
                                            channels_last=0)
    producer = _reorder_model(["a"], ["x", "y"], [helper.make_node("Relu", ["a"], ["x"]),
                                                   helper.make_node("Relu", ["a"], ["y"])])
    # x: only converted by its reader; y: also read as it is (stays plain)
    reader = _reorder_model(["x", "y"], ["out"], [reorder("x", "t"), helper.make_node("Relu", ["t"], ["u"]),
                                                   reorder("y", "v"), helper.make_node("Add", ["y", "v"], ["w"]),
                                                   helper.make_node("Add", ["u", "w"], ["out"])])
    handed = hand_off_blocked([producer, reader], [["a"], ["x", "y"]], [["x", "y"], ["out"]])
    assert handed == ["x"]
    assert [o.name for o in producer.graph.output] == ["y", "x" + SUFFIX]   # x's plain form no longer leaves
    assert [n.op_type for n in producer.graph.node] == ["Relu", "Relu", "ReorderInput"]
    assert sorted(i.name for i in reader.graph.input) == ["x" + SUFFIX, "y"]
    assert [list(n.input) for n in reader.graph.node if n.op_type == "Relu"] == [["x" + SUFFIX]]


def _quantized_pair(reader_scale=0.5, reader_extra=False, reader_transposes=True, producer_nhwc=True):
    """A producer that dequantizes its uint8 tensor, made by transposing a channels-last one
    (``producer_nhwc``) or channels-first and transposed for a head of its own, and a reader that
    quantizes it again (with ``reader_scale``) and transposes it channels-last."""
    from onnx import TensorProto, helper, numpy_helper
    const = lambda name, v: numpy_helper.from_array(np.array(v), name)  # noqa: E731
    made = ([helper.make_node("Identity", ["a"], ["h"]),
             helper.make_node("Transpose", ["h"], ["tq"], perm=[0, 3, 1, 2])]
            if producer_nhwc else [helper.make_node("Identity", ["a"], ["tq"]),
                                   helper.make_node("Transpose", ["tq"], ["th"], perm=[0, 2, 3, 1]),
                                   helper.make_node("Identity", ["th"], ["head"])])
    producer = helper.make_graph(
        made + [helper.make_node("DequantizeLinear", ["tq", "s", "z"], ["x"])], "p",
        [helper.make_tensor_value_info("a", TensorProto.UINT8, None)],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ["x"] + ["head"] * (not producer_nhwc)],
        [const("s", np.float32(0.5)), const("z", np.uint8(3))])
    nodes = [helper.make_node("QuantizeLinear", ["x", "s2", "z2"], ["q"])]
    nodes += ([helper.make_node("Transpose", ["q"], ["t"], perm=[0, 2, 3, 1])] if reader_transposes
              else [helper.make_node("Identity", ["q"], ["t"])])
    nodes.append(helper.make_node("Identity", ["t"], ["out"]))
    if reader_extra:   # the float tensor is also read as it is
        nodes.append(helper.make_node("Relu", ["x"], ["extra"]))
    reader = helper.make_graph(
        nodes, "r", [helper.make_tensor_value_info("x", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info(n, TensorProto.UINT8, None) for n in ["out"] + ["extra"] * reader_extra],
        [const("s2", np.float32(reader_scale)), const("z2", np.uint8(3))])
    return helper.make_model(producer), helper.make_model(reader)


def test_int8_stages_hand_over_uint8_where_both_sides_quantize_alike():
    producer, reader = _quantized_pair()
    assert hand_off_quantized([producer, reader], [["a"], ["x"]], [["x"], ["out"]]) == {"x": "uint8 nhwc"}
    # the producer hands its channels-last tensor; neither the transposes nor the (de)quantize remain
    assert [o.name for o in producer.graph.output] == ["x" + UINT8_NHWC_SUFFIX]
    assert [n.op_type for n in producer.graph.node] == ["Identity"]
    assert [i.name for i in reader.graph.input] == ["x" + UINT8_NHWC_SUFFIX]
    assert [(n.op_type, list(n.input)) for n in reader.graph.node] == [("Identity", ["x" + UINT8_NHWC_SUFFIX])]

    producer, reader = _quantized_pair(producer_nhwc=False)   # the producer's own transpose, for its head
    assert hand_off_quantized([producer, reader], [["a"], ["x"]], [["x", "head"], ["out"]]) == {"x": "uint8 nhwc"}
    assert [o.name for o in producer.graph.output] == ["head", "x" + UINT8_NHWC_SUFFIX]
    assert [(n.op_type, list(n.output)) for n in producer.graph.node] == [
        ("Identity", ["x" + UINT8_SUFFIX]), ("Transpose", ["x" + UINT8_NHWC_SUFFIX]), ("Identity", ["head"])]

    producer, reader = _quantized_pair(reader_transposes=False)   # read channels-first: the plain uint8 tensor
    assert hand_off_quantized([producer, reader], [["a"], ["x"]], [["x"], ["out"]]) == {"x": "uint8"}
    assert [o.name for o in producer.graph.output] == ["x" + UINT8_SUFFIX]
    assert [n.op_type for n in producer.graph.node] == ["Identity", "Transpose"]

    for kwargs in ({"reader_scale": 0.25}, {"reader_extra": True}):   # another scale; the float read too
        producer, reader = _quantized_pair(**kwargs)
        before = (producer.SerializeToString(), reader.SerializeToString())
        assert hand_off_quantized([producer, reader], [["a"], ["x"]], [["x"], ["out"]]) == {}
        assert (producer.SerializeToString(), reader.SerializeToString()) == before


def test_a_past_deadline_answers_with_the_scan_and_one_watchdog_serves_every_run(paper_export):
    runner = AnytimeRunner(paper_export)
    img, scan = _inputs()
    full = min(_timed(lambda: runner.run(img, scan)) for _ in range(3))  # noqa: F821 (runner is deleted only below)
    # the deadline has passed when the first stage starts: no stage runs to its end
    res = runner.run(img, scan, deadline_ms=0.0)
    assert res.path == 0 and res.halted
    cut = min(_timed(lambda: runner.run(img, scan, deadline_ms=0.0)) for _ in range(3))  # noqa: F821 (as above)
    assert cut < full
    np.testing.assert_allclose(res.depth, runner.depths(img, scan)[0])
    watchdog = runner._watchdog._thread
    for _ in range(3):
        runner.run(img, scan, deadline_ms=1000.0)
    assert runner._watchdog._thread is watchdog and watchdog.is_alive()
    del runner, res
    gc.collect()
    watchdog.join(timeout=5)
    assert not watchdog.is_alive()   # it ends with its runner


def _timed(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def test_the_watchdog_halts_at_each_deadline_and_is_woken_only_for_an_earlier_one():
    from explorer.deploy.runtime import _Watchdog
    halted = []
    dog = _Watchdog(lambda: halted.append(time.perf_counter()))
    wakes = []
    notify = dog._cond.notify
    dog._cond.notify = lambda *a: (wakes.append(1), notify(*a))
    try:
        start = time.perf_counter()
        dog.arm(start + 0.4)
        time.sleep(0.1)        # the thread starts and waits for that deadline
        dog.disarm()
        dog.arm(start + 0.7)   # later than the wait it is in: it finds this deadline when that wait ends
        assert len(wakes) == 1
        while not halted and time.perf_counter() < start + 10:
            time.sleep(0.01)
        assert len(halted) == 1 and halted[0] >= start + 0.7
        far = time.perf_counter() + 30
        dog.arm(far)
        dog.disarm()
        soon = time.perf_counter() + 0.1
        dog.arm(soon)          # earlier than the wait it is in: woken
        assert len(wakes) == 3
        while len(halted) < 2 and time.perf_counter() < soon + 10:
            time.sleep(0.01)
        assert len(halted) == 2 and soon <= halted[1] < far
    finally:
        dog.stop()
