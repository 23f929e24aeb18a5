"""Measuring on this machine with onnxruntime: per stage, per path, and the whole graph."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from explorer import probe as _probe
from explorer.calibration.peak import host_peak
from explorer.deploy.sessions import session  # noqa: F401  (measurements and the runtime: one kind of session)
from explorer.model.network import AnytimeDepthNet, build_network
from explorer.model.onnx import example_inputs, export_stages, export_whole
from explorer.probe import DEFAULT_PROVIDER, default_threads, time_call
from explorer.space import Candidate

__all__ = ["session", "default_threads", "time_call", "conditions", "Measurement", "CandidateTimer", "measure_network",
           "measure_candidate", "DEFAULT_PROVIDER"]


def conditions(threads: int | None = None, repeats: int = 15, warmup: int = 3,
               provider: str = DEFAULT_PROVIDER) -> dict:
    import platform

    import onnxruntime as ort
    return {"onnxruntime": ort.__version__, "provider": provider,
            "threads": _probe.shared_pool_threads() or threads or default_threads(), "thread_pool": _probe.thread_pool(),
            "repeats": repeats,
            "warmup": warmup, "statistic": "median", "machine": platform.machine(),
            "processor": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "peak": host_peak().to_dict()}


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


class CandidateTimer:
    """A network's stage graphs in one chain, as the probe times them and the runtime runs them
    (tensors handed over blocked, in sequence: ``probe_script.chain_sessions``, ``time_chain``), and
    (``whole``) the whole network as one graph, with their sessions built once: ``measure`` times them
    again as often as asked, so that several candidates can be measured in interleaved rounds."""

    def __init__(self, net: AnytimeDepthNet, input_size: tuple[int, int] = (224, 224), threads: int | None = None,
                 whole: bool = True, provider: str = DEFAULT_PROVIDER) -> None:
        self.candidate, self.input_size = net.candidate, tuple(input_size)
        self.threads, self.provider = threads, provider
        graphs = export_stages(net, input_size)
        self._specs = [spec for spec, _ in graphs]
        env = {k: v.numpy() for k, v in example_inputs(input_size).items()}
        chain = _probe.chain_sessions([model for _, model in graphs], threads, provider)
        self._runs, self._new_round = _probe.chain_runs(chain, env)
        self._whole = None
        if whole:
            sess = session(export_whole(net, input_size), threads, provider)
            feeds = {"image": env["image"], "scan": env["scan"]}
            self._whole = lambda: sess.run(None, feeds)

    def measure(self, repeats: int = 15, warmup: int = 3) -> Measurement:
        stage_ms: dict[str, float] = {}
        path_ms = [0.0]
        elapsed = 0.0
        for spec, ms in zip(self._specs, _probe.time_chain(self._runs, warmup, repeats, new_round=self._new_round)):
            if spec is None:
                path_ms[0] = ms
                continue
            stage_ms[spec.name] = ms
            elapsed += ms
            if spec.path is not None:
                path_ms.append(elapsed)
        whole_ms = time_call(self._whole, warmup, repeats) if self._whole is not None else float("nan")
        return Measurement(self.candidate, self.input_size, stage_ms, path_ms, whole_ms,
                           conditions(self.threads, repeats, warmup, self.provider))


def measure_network(net: AnytimeDepthNet, input_size: tuple[int, int] = (224, 224),
                    threads: int | None = None, repeats: int = 15, warmup: int = 3,
                    whole: bool = True, provider: str = DEFAULT_PROVIDER) -> Measurement:
    """Times every stage graph with onnxruntime, in one chain as the probe times them, and (``whole``)
    the whole network as one graph (``CandidateTimer``, measured once)."""
    return CandidateTimer(net, input_size, threads, whole, provider).measure(repeats, warmup)


def measure_candidate(candidate: Candidate, input_size: tuple[int, int] = (224, 224),
                      threads: int | None = None, repeats: int = 15,
                      provider: str = DEFAULT_PROVIDER) -> Measurement:
    return measure_network(build_network(candidate), input_size, threads, repeats, provider=provider)
