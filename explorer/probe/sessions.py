"""onnxruntime sessions as every measurement and the runtime use them: one shared thread pool and
memory arena per process, the execution provider checked first."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None

from .formats import DEFAULT_PROVIDER, ProbeError
from .rewrites import NCHWC_DOMAIN, _onnx, blocked_skip_adds, channels_last_skip_adds
from .scratch import scratch_dir


# -- sessions -------------------------------------------------------------------------
def default_threads() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def check_provider(provider: str) -> None:
    import onnxruntime as ort
    have = ort.get_available_providers()
    if provider not in have:
        raise ProbeError(f"execution provider {provider} is not in this onnxruntime {ort.__version__} "
                         f"(it has {', '.join(have)}); install the onnxruntime build that has it, or pick one of those")


#: Environment variable: "session" gives every session its own thread pool instead of the shared one
#: (for programs that also create onnxruntime sessions of their own, which a global pool forbids).
POOL_ENV = "EXPLORER_ORT_POOL"
_POOL: dict[str, "int | bool | None"] = {}   # "threads" of the shared pool; "arena": one shared arena


def shared_pool_threads() -> "int | None":
    """Threads of onnxruntime's global intra-op pool when this process's sessions share it, else None."""
    return _POOL.get("threads")


def shared_arena() -> bool:
    """Whether this process's sessions allocate from one shared memory arena (``_shared_arena``)."""
    return bool(_POOL.get("arena"))


def thread_pool() -> str:
    """What measurement conditions record: 'shared' or 'per-session'."""
    return "shared" if shared_pool_threads() else "per-session"


def _shared_pool(threads: int) -> bool:
    """Every session of this process shares onnxruntime's one global intra-op pool, created by the
    first session. Stages run one after another, so one pool serves them all, and its threads spin
    between operators. Pools of their own either sleep between operators (waking them takes longer
    in some sessions than in others: bimodal timings) or, spinning, fight each other for the cores
    (much slower with a dozen stage sessions alive)."""
    if "threads" not in _POOL:
        _POOL["threads"] = None
        if os.environ.get(POOL_ENV, "shared") != "session":
            import onnxruntime as ort
            try:
                ort.set_global_thread_pool_sizes(threads, 1)
                _POOL["threads"] = threads
            except AttributeError:   # an onnxruntime without global pools: per-session ones
                pass
            except Exception:   # someone in this process made the global pools already: share them
                _POOL["threads"] = threads
            if _POOL["threads"] is not None:
                _POOL["arena"] = _shared_arena(ort)
    return _POOL["threads"] is not None


def _shared_arena(ort) -> bool:
    """Registers one CPU memory arena for every session of the process to allocate from. On a calm
    machine the paper design's stage sessions run faster with one shared arena than with arenas of
    their own: buffers are reused from stage to stage instead of each stage keeping its own apart. On
    a machine slowed by other loads it can go the other way, so the runtime keeps both and picks per
    run (``explorer.deploy._arena_choice``)."""
    try:
        info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
        ort.create_and_register_allocator(info, ort.OrtArenaCfg(0, -1, -1, -1))
        return True
    except AttributeError:   # an onnxruntime without shared allocators
        return False
    except Exception:   # registered already in this process: share it
        return True


def session(model: "bytes | str | Path", threads: int | None = None, provider: str = DEFAULT_PROVIDER,
            optimize: bool = True, save_optimized: "Path | None" = None, own_arena: bool = False,
            blocked_skips: bool = True):
    """An onnxruntime session as every measurement and the runtime use it: ``threads`` intra-op
    threads (the process's shared pool has those of its first session) and, with that pool, the
    process's one memory arena (``_shared_arena``; ``own_arena``: one of its own instead), full graph
    optimisation (none for a graph optimised already; ``save_optimized``: where to write the optimised
    graph), then, on the CPU provider, the decoder's skip additions kept in the blocked layout
    (``blocked_skip_adds``; ``blocked_skips=False``: as onnxruntime left them), ``provider`` first
    (the CPU one takes what it cannot run)."""
    if optimize and blocked_skips and provider == DEFAULT_PROVIDER and _onnx() is not None:
        with scratch_dir("session") as tmp:
            optimized = Path(tmp) / "optimized.onnx"
            sess = _session(model, threads, provider, True, optimized, own_arena)
            graph = _onnx().load(str(optimized))
            if not blocked_skip_adds(graph, block_size()) + channels_last_skip_adds(graph):
                if save_optimized is not None:
                    shutil.copyfile(optimized, save_optimized)
                return sess
        rewritten = graph.SerializeToString()
        if save_optimized is not None:
            Path(save_optimized).write_bytes(rewritten)
        return _session(rewritten, threads, provider, False, None, own_arena)
    return _session(model, threads, provider, optimize, save_optimized, own_arena)


def _session(model, threads, provider, optimize, save_optimized, own_arena):
    import onnxruntime as ort
    opts = ort.SessionOptions()
    threads = threads or default_threads()
    if _shared_pool(threads):
        opts.use_per_session_threads = False
        if _POOL.get("arena") and not own_arena:
            opts.add_session_config_entry("session.use_env_allocators", "1")
    else:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        # Stages run one after another in separate sessions: threads spinning after one stage would
        # steal the cores from the next.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                     else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    if save_optimized is not None:
        opts.optimized_model_filepath = str(save_optimized)
    opts.log_severity_level = 3
    providers = [provider] + ([DEFAULT_PROVIDER] if provider != DEFAULT_PROVIDER else [])
    return ort.InferenceSession(str(model) if isinstance(model, Path) else model, opts, providers=providers)


def block_size() -> int:
    """onnxruntime's channel block on this machine (8 with AVX2, 16 with AVX-512): what 4 channels
    are padded to by its ReorderInput."""
    if "block" not in _POOL:
        from onnx import TensorProto, helper
        x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 1, 1])
        y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
        node = helper.make_node("ReorderInput", ["x"], ["y"], domain=NCHWC_DOMAIN, channels_last=0)
        model = helper.make_model(helper.make_graph([node], "block", [x], [y]),
                                  opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(NCHWC_DOMAIN, 1)],
                                  ir_version=8)   # opset 17's: onnx's newest may be past what onnxruntime reads
        sess = _session(model.SerializeToString(), None, DEFAULT_PROVIDER, False, None, False)
        _POOL["block"] = int(sess.run(None, {"x": np.zeros((1, 4, 1, 1), np.float32)})[0].shape[1])
    return int(_POOL["block"])
