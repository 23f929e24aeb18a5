"""What each path of a candidate costs: parameters and MACs from its workloads, latency and energy
from a device profile. Paths are prefixes of one execution, so costs accumulate stage by stage."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from explorer.cost.devices import (
    DeviceProfile,
    available_devices,
    deployed_graphs,
    get_device,
    int8_graphs,
    path_latencies_ms,
)
from explorer.cost.workloads import (
    KINDS,
    Workload,
    candidate_workloads,
    dilated_count_macs,
    reference_workloads,
)
from explorer.model.network import stage_specs
from explorer.model.reference import REFERENCES, ReferenceModel
from explorer.space import Candidate

__all__ = ["CandidateCost", "DeviceProfile", "KINDS", "Workload", "available_devices",
           "candidate_cost", "candidate_workloads", "dilated_count_macs", "get_device", "model_cost", "profile_candidate", "profile_reference",
           "reference_cost", "reference_table",
           "reference_workloads"]


@dataclass(frozen=True)
class CandidateCost:
    """Workloads of a candidate at one input size, and which stages each path needs."""

    candidate: Candidate
    input_size: tuple[int, int]
    workloads: tuple[Workload, ...]
    path_stages: tuple[tuple[str, ...], ...]   # for paths 1..K
    path_exits: tuple[str, ...]

    def stage_totals(self) -> dict[str, tuple[int, int]]:
        """(params, MACs) per stage, in execution order."""
        totals: dict[str, list[int]] = {}
        for w in self.workloads:
            t = totals.setdefault(w.stage, [0, 0])
            t[0] += w.params
            t[1] += w.macs
        return {k: (v[0], v[1]) for k, v in totals.items()}

    def path_params_macs(self) -> list[tuple[int, int]]:
        """Cumulative (params, MACs) at each path, path 0 (0, 0) included."""
        totals = self.stage_totals()
        out = [(0, 0)]
        for stages in self.path_stages:
            out.append((sum(totals.get(s, (0, 0))[0] for s in stages),
                        sum(totals.get(s, (0, 0))[1] for s in stages)))
        return out

    @property
    def precision(self) -> str:
        return self.candidate.precision

    def int8_graphs(self, device: DeviceProfile) -> tuple[str, ...]:
        """Names of the deployed stage graphs (``stage+stage+...``, as an export names them) that an int8
        export of this candidate keeps int8 on ``device``: none for an fp32 candidate."""
        if self.precision != "int8":
            return ()
        graphs = deployed_graphs(self.path_stages)
        keep = int8_graphs(device.at_precision("int8"), self.workloads, self.path_stages)
        return tuple("+".join(g) for g, k in zip(graphs, keep) if k)

    def path_latency_ms(self, device: DeviceProfile) -> list[float]:
        """Ready time of each path on ``device`` at the candidate's precision, path 0 (0 ms) included."""
        return [0.0] + path_latencies_ms(device.at_precision(self.precision), self.workloads, self.path_stages)

    def path_energy_j(self, device: DeviceProfile) -> list[float]:
        return [float(device.energy_j(t)) for t in self.path_latency_ms(device)]

    def path_costs(self, device: DeviceProfile, kind: str) -> list[float]:
        """Costs in a budget's unit: ms for 'time', J for 'energy'."""
        return self.path_latency_ms(device) if kind == "time" else self.path_energy_j(device)


def candidate_cost(candidate: Candidate, input_size: tuple[int, int] = (224, 224),
                   paper_graph: bool = False) -> CandidateCost:
    """``paper_graph``: the costs of the graph of ``candidate`` that the paper measured, whose last
    decoder stage up-samples before its exit head and whose exits up-sample with a bilinear resize
    operator (``stage_specs``), for the paper's figures."""
    specs = stage_specs(candidate, paper_graph)
    workloads = candidate_workloads(candidate, input_size, specs)
    path_stages, exits, done = [], [], []
    for spec in specs:
        done.append(spec.name)
        if spec.path is not None:
            path_stages.append(tuple(done))
            exits.append(spec.name)
    return CandidateCost(candidate, tuple(input_size), tuple(workloads), tuple(path_stages), tuple(exits))


def reference_cost(name: str, input_size: tuple[int, int] = (224, 224)) -> CandidateCost:
    """A reference network (:mod:`explorer.model.reference`) costed as a candidate with one path
    beside path 0: what a study needs to score it as a baseline."""
    return CandidateCost(ReferenceModel(name), tuple(input_size), reference_workloads(name, tuple(input_size)),
                         (("network",),), ("output",))


def model_cost(model, input_size: tuple[int, int] = (224, 224)) -> CandidateCost:
    """:func:`candidate_cost` for a candidate, :func:`reference_cost` for a reference network."""
    if isinstance(model, Candidate):
        return candidate_cost(model, input_size)
    return reference_cost(model.name, input_size)


def profile_candidate(candidate: Candidate, input_size: tuple[int, int] = (224, 224),
                      device: str | Path | DeviceProfile | None = None) -> pd.DataFrame:
    """One row per path (path 0 included): exit, params, macs, and latency_ms / energy_j when a
    device profile (name, file or object) is given."""
    cost = candidate_cost(candidate, input_size)
    pm = cost.path_params_macs()
    frame = pd.DataFrame({
        "path": range(len(pm)),
        "exit": ["scan (nearest)"] + list(cost.path_exits),
        "params": [p for p, _ in pm],
        "macs": [m for _, m in pm],
    })
    if device is not None:
        profile = get_device(device)
        frame["latency_ms"] = cost.path_latency_ms(profile)
        frame["energy_j"] = cost.path_energy_j(profile)
    return frame


def profile_reference(name: str, input_size: tuple[int, int] = (224, 224),
                      device: str | Path | DeviceProfile | None = None) -> pd.DataFrame:
    """The reference network ``name`` (``explorer.model.reference.REFERENCES``) as one path: params,
    macs, and latency_ms / energy_j when a device profile is given. A network with transposed
    convolutions also has ``macs_dilated``: its multiply-adds as FLOP counters count them (see
    ``dilated_count_macs``), the convention of the paper's GFLOPs."""
    workloads = reference_workloads(name, tuple(input_size))
    frame = pd.DataFrame({"path": [1], "exit": ["output"], "params": [sum(w.params for w in workloads)],
                          "macs": [sum(w.macs for w in workloads)]})
    if any(w.kind == "deconv" for w in workloads):
        frame["macs_dilated"] = [dilated_count_macs(workloads)]
    if device is not None:
        profile = get_device(device)
        latency = path_latencies_ms(profile, workloads, [("network",)])
        frame["latency_ms"] = latency
        frame["energy_j"] = [float(profile.energy_j(t)) for t in latency]
    return frame


def reference_table(devices: list[str | Path | DeviceProfile]) -> pd.DataFrame:
    """The paper's reference networks at the input size the paper measured them at: params, MACs,
    the paper's TX2 latency, and latency (energy where the device models it) on each device."""
    profiles = [get_device(d) for d in devices]
    rows = []
    for ref in REFERENCES.values():
        if ref.paper is None:
            continue
        h, w = ref.paper.input_size
        frame = profile_reference(ref.name, ref.paper.input_size)
        row = {"network": ref.name, "input": f"{h}x{w}", "params": int(frame["params"][0]),
               "macs": int(frame["macs"][0]), "paper TX2 ms": ref.paper.latency_ms}
        workloads = reference_workloads(ref.name, ref.paper.input_size)
        for p in profiles:
            ms = path_latencies_ms(p, workloads, [("network",)])[0]
            row[f"{p.name} ms"] = ms
            if p.active_power_w > 0:
                row[f"{p.name} J"] = float(p.energy_j(ms))
        rows.append(row)
    return pd.DataFrame(rows)
