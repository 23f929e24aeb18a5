"""Every onnxruntime session of a process shares the global intra-op pool and one memory arena
(explorer.probe), and quantization, whose own sessions a shared pool forbids, still
works there. Each case runs in a fresh interpreter: the pool is per process, and this test process
has made sessions already."""

import json
import os
import subprocess
import sys

SCRIPT = r"""
import json, sys
from explorer.calibration.sweep import SweepLayer, layer_graph
from explorer.calibration.measure import conditions
from explorer.probe import session, shared_pool_threads
from explorer.deploy.int8_graphs import quantize_graph
import tempfile, pathlib
model, feeds, _ = layer_graph(SweepLayer("pointwise", (48, 14, 14), 8))   # 48 products per output: quantized
first = session(model, 2)
second = session(model, 1)   # a later size cannot change the pool's
def arena(sess):
    try:
        return sess.get_session_options().get_session_config_entry("session.use_env_allocators")
    except Exception:   # not set
        return None
out = {"pool": shared_pool_threads(), "conditions": conditions()["thread_pool"],
       "same": bool((first.run(None, feeds)[0] == second.run(None, feeds)[0]).all()),
       "arena": [arena(first), arena(second)]}
with tempfile.TemporaryDirectory() as tmp:
    src, dst = pathlib.Path(tmp) / "a.onnx", pathlib.Path(tmp) / "b.onnx"
    src.write_bytes(model)
    out["quantized"] = quantize_graph(src, dst, [feeds])
    q = session(dst.read_bytes())
    out["int8_shape"] = list(q.run(None, feeds)[0].shape)
print(json.dumps(out))
"""


def _run(env_extra: dict) -> dict:
    env = {**os.environ, **env_extra}
    run = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_sessions_share_one_pool_and_quantization_still_works():
    out = _run({"EXPLORER_ORT_POOL": "shared"})
    assert out == {"pool": 2, "conditions": "shared", "same": True, "quantized": True, "int8_shape": [1, 8, 14, 14],
                   "arena": ["1", "1"]}   # and one memory arena


def test_per_session_pools_on_request():
    out = _run({"EXPLORER_ORT_POOL": "session"})
    assert out["pool"] is None and out["conditions"] == "per-session"
    assert "1" not in out["arena"]   # arenas of their own too
    assert out["quantized"] is True and out["int8_shape"] == [1, 8, 14, 14]
