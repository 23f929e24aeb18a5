import gc
import platform
import time

import numpy as np
import pytest
import torch

from explorer._layout import SUFFIX, hand_off_blocked
from explorer.deploy import export_network
from explorer.model import build_network
from explorer.runtime import AnytimeRunner
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
    blocked, plain = AnytimeRunner(paper_export), AnytimeRunner(paper_export, blocked_handoff=False)
    assert plain.handed_off == []
    if platform.machine() in ("x86_64", "AMD64"):   # onnxruntime blocks channels on x86 (AVX2 and up)
        # the decoder's running feature map, read by the next decoder (x0, x1, x2), and the encoder's skips,
        # which each decoder adds blocked (``probe_script.blocked_skip_adds``)
        assert blocked.handed_off == ["x0", "skip_s8", "x1", "skip_s4", "x2", "skip_s2"]
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


def test_a_past_deadline_answers_with_the_scan_and_one_watchdog_serves_every_run(paper_export):
    runner = AnytimeRunner(paper_export)
    img, scan = _inputs()
    full = min(_timed(lambda: runner.run(img, scan)) for _ in range(3))
    # the deadline has passed when the first stage starts: no stage runs to its end
    res = runner.run(img, scan, deadline_ms=0.0)
    assert res.path == 0 and res.halted
    cut = min(_timed(lambda: runner.run(img, scan, deadline_ms=0.0)) for _ in range(3))
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
