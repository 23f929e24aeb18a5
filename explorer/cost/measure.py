"""Measuring on this machine with onnxruntime: per stage, per path, and the whole graph."""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass, field
from typing import Callable


from explorer.model.network import AnytimeDepthNet, build_network
from explorer.space import Candidate


def session(model: bytes, threads: int | None = None):
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads or default_threads()
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    # Stages run one after another in separate sessions: threads spinning after one stage would
    # steal the cores from the next.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])


def default_threads() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def time_call(fn: Callable[[], object], warmup: int = 3, repeats: int = 15) -> float:
    """Median wall time of ``fn`` in ms after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(samples)


def conditions(threads: int | None = None, repeats: int = 15, warmup: int = 3) -> dict:
    import onnxruntime as ort
    import platform
    return {"onnxruntime": ort.__version__, "threads": threads or default_threads(), "repeats": repeats,
            "warmup": warmup, "statistic": "median", "machine": platform.machine(),
            "processor": platform.processor() or platform.machine(), "cores": os.cpu_count()}


@dataclass
class Measurement:
    candidate: Candidate
    input_size: tuple[int, int]
    stage_ms: dict[str, float]
    path_ms: list[float]          # path 0 included (its own tiny graph)
    whole_ms: float
    conditions: dict = field(default_factory=dict)

    @property
    def staged_total_ms(self) -> float:
        return sum(self.stage_ms.values())

    @property
    def staging_overhead(self) -> float:
        """(sum of stages) / (whole graph) - 1."""
        return self.staged_total_ms / self.whole_ms - 1.0


def measure_network(net: AnytimeDepthNet, input_size: tuple[int, int] = (224, 224),
                    threads: int | None = None, repeats: int = 15, warmup: int = 3,
                    whole: bool = True) -> Measurement:
    """Times every stage graph with onnxruntime, and (``whole``) the whole network as one graph."""
    from explorer.onnx_stages import example_inputs, export_stages, export_whole
    graphs = export_stages(net, input_size)
    env = {k: v.numpy() for k, v in example_inputs(input_size).items()}
    stage_ms: dict[str, float] = {}
    path_ms = [0.0]
    elapsed = 0.0
    for spec, model in graphs:
        sess = session(model, threads)
        names = [i.name for i in sess.get_inputs()]
        feeds = {n: env[n] for n in names}
        outs = sess.run(None, feeds)
        name = "path0" if spec is None else spec.name
        ms = time_call(lambda: sess.run(None, feeds), warmup, repeats)
        if spec is None:
            path_ms[0] = ms
            continue
        env.update({o.name: v for o, v in zip(sess.get_outputs(), outs)})
        stage_ms[name] = ms
        elapsed += ms
        if spec.path is not None:
            path_ms.append(elapsed)
    whole_ms = float("nan")
    if whole:
        sess = session(export_whole(net, input_size), threads)
        feeds = {"image": env["image"], "scan": env["scan"]}
        whole_ms = time_call(lambda: sess.run(None, feeds), warmup, repeats)
    return Measurement(net.candidate, tuple(input_size), stage_ms, path_ms, whole_ms,
                       conditions(threads, repeats, warmup))


def measure_candidate(candidate: Candidate, input_size: tuple[int, int] = (224, 224),
                      threads: int | None = None, repeats: int = 15) -> Measurement:
    return measure_network(build_network(candidate), input_size, threads, repeats)
