"""Fitting device profiles to measurements.

A fit minimises log-ratio errors (relative, so a 0.04 ms kernel counts as much as a 4 ms one) of
per-layer measurements and of end-to-end measurements (whole paths), with scipy's robust least
squares. ``python -m explorer.cost.fit --data ../shared/data`` rebuilds the shipped TX2, TX2-CPU
and Raspberry Pi 4 profiles from the measured TVM kernels and the paper's figures, and prints every
calibration figure next to its target.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from explorer.anytime import anytime_loss, parse_budget
from explorer.cost import candidate_cost
from explorer.cost.devices import PROFILES_DIR, DeviceProfile, KindCost
from explorer.cost.workloads import (
    ALL_KINDS,
    BYTES_PER_VALUE,
    Workload,
    reference_workloads,
)
from explorer.files import write_atomically
from explorer.model.reference import REFERENCES
from explorer.space import Candidate, paper_candidate

MEMORY_KINDS = ("resize", "add", "concat", "slice")


@dataclass
class Observation:
    """Measured time of running ``workloads`` (one layer, or a whole path with its overhead)."""

    label: str
    workloads: Sequence[Workload]
    measured_ms: float
    weight: float = 1.0
    end_to_end: bool = False
    stages: int = 0   # separately launched stages (graphs) in the measured run
    group: str = ""   # e.g. the input size of a stage graph: fits compare groups' biases


def kernel_workloads(csv: str | Path, target: str) -> list[tuple[Workload, float]]:
    """The measured TVM kernels of ``kernels.csv`` for ``target`` ('gpu' or 'cpu') as workloads."""
    frame = pd.read_csv(csv)
    frame = frame[frame["target"] == target]
    out = []
    for r in frame.itertuples():
        h, w = r.in_height // r.stride, r.in_width // r.stride
        groups = r.in_channels if r.kind == "depthwise" else 1
        params = r.out_channels * (r.in_channels // groups) * r.kernel ** 2
        in_n, out_n = r.in_channels * r.in_height * r.in_width, r.out_channels * h * w
        wl = Workload("kernel", f"{r.kind}{r.kernel}x{r.kernel}/{r.stride} {r.in_channels}-{r.out_channels}@{r.in_height}",
                      r.kind, (r.in_channels, r.in_height, r.in_width), (r.out_channels, h, w),
                      r.kernel, r.stride, int(r.macs), params,
                      (in_n + params) * BYTES_PER_VALUE, out_n * BYTES_PER_VALUE)
        out.append((wl, float(r.best_ms)))
    return out


class _Params:
    """Maps a vector of log-parameters to a profile. Kinds may share a rate or an overhead."""

    def __init__(self, rate_of: dict[str, str], overhead_of: dict[str, str], base: DeviceProfile,
                 free_bandwidth: bool = True, free_inference: bool = True, free_stage: bool = False,
                 own_bandwidth: tuple[str, ...] = ()) -> None:
        self.rate_of, self.overhead_of, self.base = rate_of, overhead_of, base
        self.own_bandwidth = own_bandwidth
        self.names = ([f"gmacs:{k}" for k in sorted(set(rate_of.values()))]
                      + [f"overhead:{k}" for k in sorted(set(overhead_of.values()))]
                      + [f"kbw:{k}" for k in own_bandwidth])
        if free_bandwidth:
            self.names.append("bandwidth")
        if free_inference:
            self.names.append("inference")
        if free_stage:
            self.names.append("stage")

    def initial(self) -> np.ndarray:
        b = self.base
        vals = []
        for n in self.names:
            kind, _, key = n.partition(":")
            if kind == "gmacs":
                rep = next(k for k, g in self.rate_of.items() if g == key)
                vals.append(b.kinds[rep].gmacs)
            elif kind == "overhead":
                rep = next(k for k, g in self.overhead_of.items() if g == key)
                vals.append(max(b.kinds[rep].overhead_ms, 1e-4))
            elif kind == "bandwidth":
                vals.append(b.bandwidth_gbs)
            elif kind == "kbw":
                vals.append(b.kinds[key].bandwidth_gbs or b.bandwidth_gbs)
            elif kind == "stage":
                vals.append(max(b.stage_overhead_ms, 1e-3))
            else:
                vals.append(max(b.inference_overhead_ms, 1e-3))
        return np.log(vals)

    def profile(self, x: np.ndarray) -> DeviceProfile:
        v = dict(zip(self.names, np.exp(x)))
        kinds = {}
        for k in ALL_KINDS:
            base = self.base.kinds[k]
            g = v.get(f"gmacs:{self.rate_of.get(k, '')}", base.gmacs)
            o = v.get(f"overhead:{self.overhead_of.get(k, '')}", base.overhead_ms)
            bw = v.get(f"kbw:{k}", base.bandwidth_gbs)
            kinds[k] = dataclasses.replace(base, gmacs=float(g), overhead_ms=float(o),
                                           bandwidth_gbs=None if bw is None else float(bw))
        return dataclasses.replace(
            self.base, kinds=kinds, bandwidth_gbs=float(v.get("bandwidth", self.base.bandwidth_gbs)),
            inference_overhead_ms=float(v.get("inference", self.base.inference_overhead_ms)),
            stage_overhead_ms=float(v.get("stage", self.base.stage_overhead_ms)))


def predict_ms(profile: DeviceProfile, obs: Observation) -> float:
    t = float(profile.latencies_ms(obs.workloads).sum()) + obs.stages * profile.stage_overhead_ms
    return t + (profile.inference_overhead_ms if obs.end_to_end else 0.0)


class ObservationBatch:
    """Observations' workloads as arrays, priced by a profile all at once: ``predict_ms`` as
    ``DeviceProfile.layer_ms`` computes it, one observation per entry. A fit prices every observation
    for each of its thousands of residual evaluations; one Python call per workload made the host fit
    a large share of a quick calibration (bench_fit compares the two pricings)."""

    def __init__(self, observations: Sequence[Observation]) -> None:
        rows = [(i, w) for i, o in enumerate(observations) for w in o.workloads]
        self.kinds = sorted({w.kind for _, w in rows})
        index = {k: j for j, k in enumerate(self.kinds)}
        self.count = len(observations)
        self._obs = np.array([i for i, _ in rows], dtype=np.int64)
        self._kind = np.array([index[w.kind] for _, w in rows], dtype=np.int64)
        self._macs = np.array([w.macs for _, w in rows], dtype=float)
        written = np.array([w.bytes_written for _, w in rows], dtype=float)
        self._moved = np.array([w.bytes_read for _, w in rows], dtype=float) + written
        params = np.array([w.params for _, w in rows], dtype=float)
        self._moved_without_weights = np.maximum(self._moved - params * BYTES_PER_VALUE, written)
        self._stages = np.array([o.stages for o in observations], dtype=float)
        self._end_to_end = np.array([o.end_to_end for o in observations], dtype=bool)

    def predict_ms(self, profile: DeviceProfile) -> np.ndarray:
        costs = [profile.kinds[k] for k in self.kinds]
        gmacs = np.array([c.gmacs for c in costs])[self._kind]
        overhead = np.array([c.overhead_ms for c in costs])[self._kind]
        bandwidth = np.array([c.bandwidth_gbs or profile.bandwidth_gbs for c in costs])[self._kind]
        weights_move = np.array([c.weight_traffic for c in costs], dtype=bool)[self._kind]
        compute = self._macs / (gmacs * 1e6)
        memory = np.where(weights_move, self._moved, self._moved_without_weights) / (bandwidth * 1e6)
        body = np.maximum(compute, memory) if profile.overlap else compute + memory
        if profile.body_exponent != 1.0:
            body = body ** profile.body_exponent
        layers = np.bincount(self._obs, weights=overhead + body, minlength=self.count)
        return (layers + self._stages * profile.stage_overhead_ms
                + np.where(self._end_to_end, profile.inference_overhead_ms, 0.0))


def fit_profile(base: DeviceProfile, observations: Sequence[Observation],
                rate_of: dict[str, str], overhead_of: dict[str, str],
                free_bandwidth: bool = True, free_inference: bool = True,
                free_stage: bool = False, own_bandwidth: tuple[str, ...] = ()) -> DeviceProfile:
    params = _Params(rate_of, overhead_of, base, free_bandwidth, free_inference, free_stage, own_bandwidth)
    x0 = params.initial()
    weights = np.array([o.weight for o in observations])
    measured = np.log([o.measured_ms for o in observations])
    batch = ObservationBatch(observations)

    def residuals(x: np.ndarray) -> np.ndarray:
        pred = np.log(np.maximum(batch.predict_ms(params.profile(x)), 1e-9))
        prior = 0.01 * (x - x0)  # keeps parameters that the data barely see near their start
        return np.concatenate([weights * (pred - measured), prior])

    result = least_squares(residuals, x0, loss="soft_l1", f_scale=0.2, bounds=(x0 - 12, x0 + 12))
    return params.profile(result.x)


def errors(profile: DeviceProfile, observations: Sequence[Observation]) -> pd.DataFrame:
    measured = np.array([o.measured_ms for o in observations], dtype=float)
    pred = ObservationBatch(observations).predict_ms(profile)
    return pd.DataFrame({"what": [o.label for o in observations], "measured_ms": measured,
                         "predicted_ms": pred, "error": pred / measured - 1.0})


def fit_summary(frame: pd.DataFrame, name: str) -> dict:
    err = frame["error"].abs()
    return {"what": name, "count": int(len(frame)), "median_abs_error": round(float(err.median()), 4),
            "max_abs_error": round(float(err.max()), 4),
            "within_10pct": round(float((err <= 0.10).mean()), 3)}


# -- the shipped profiles -------------------------------------------------------------------------
PAPER_TX2_PATHS_MS = (6.4, 8.0, 9.8, 12.2)
PAPER_TABLE1_RMSE = (0.9871, 0.4651, 0.4225, 0.4184, 0.4156)
PAPER_RPI4_TABLE2 = {"time:uniform:100ms": 0.755, "time:uniform:50ms": 0.987, "time:uniform:33ms": 0.987,
                     "energy:uniform:0.5J": 0.582, "energy:uniform:0.25J": 0.746}
MOBILENET_RPI4_MS = 72.0


def _start(name: str, description: str, overlap: bool, gmacs: float, overhead: float, bw: float) -> DeviceProfile:
    return DeviceProfile(name=name, description=description, overlap=overlap, bandwidth_gbs=bw,
                         kinds={k: KindCost(gmacs, overhead) for k in ALL_KINDS}, inference_overhead_ms=0.1)


def _path_observations(weight: float, targets) -> list[Observation]:
    obs = []
    for label, candidate, paths_ms in targets:
        cost = candidate_cost(candidate, paper_graph=True)   # the graph the paper measured
        for i, (stages, ms) in enumerate(zip(cost.path_stages, paths_ms), start=1):
            wl = [w for w in cost.workloads if w.stage in stages]
            obs.append(Observation(f"{label} path {i}", wl, ms, weight, end_to_end=True))
    return obs


#: The paper's end-to-end TX2 GPU figures of reference networks (Tables 1 and 3), by name.
TX2_REFERENCES = ("fastdepth", "s2d-resnet50", "s2d-resnet18", "monodepth2-resnet18")
#: fast-depth's own figures for its NetAdapt-pruned model (TVM, TX2): GPU and CPU end to end.
PRUNED_FASTDEPTH_MS = {"gpu": 5.6, "cpu": 37.0}
#: Sizes at which the paper gives the paper design's path 4 without a latency (Tables 1, 3): the
#: profile's predictions there are recorded (not fitted) so a reader sees how it scales.
SCALING_SIZES = ((224, 320), (192, 640), (224, 896))


def _reference_observations(names: Sequence[str], weight: float) -> list[Observation]:
    obs = []
    for name in names:
        paper = REFERENCES[name].paper
        h, w = paper.input_size
        obs.append(Observation(f"{name} at {h}x{w}", reference_workloads(name, paper.input_size),
                               paper.latency_ms, weight, end_to_end=True))
    return obs


def _pruned_fastdepth(target: str) -> Observation:
    return Observation("fastdepth-pruned at 224x224 (fast-depth's figure)",
                       reference_workloads("fastdepth-pruned", (224, 224)), PRUNED_FASTDEPTH_MS[target],
                       end_to_end=True)


def _scaling_rows(profile: DeviceProfile) -> list[dict]:
    at224 = candidate_cost(paper_candidate()).path_latency_ms(profile)[-1]
    rows = []
    for size in SCALING_SIZES:
        t = candidate_cost(paper_candidate(), size).path_latency_ms(profile)[-1]
        rows.append({"what": f"paper design path 4 at {size[0]}x{size[1]} (no published latency)",
                     "predicted_ms": round(t, 3), "times_224x224": round(t / at224, 3)})
    return rows


#: How the TVM kernels' kinds share fitted parameters. The kernels do not tell one-channel pointwise
#: layers apart, so those share the pointwise rate; memory-bound kinds share one launch overhead.
TX2_RATE_OF = {"conv": "conv", "pointwise": "pointwise", "pointwise_1ch": "pointwise", "depthwise": "depthwise",
               "conv1d": "conv", "resize": "resize", "deconv": "deconv"}
TX2_OVERHEAD_OF = {"conv": "conv", "pointwise": "pointwise", "pointwise_1ch": "pointwise", "depthwise": "depthwise",
                   "conv1d": "depthwise", "deconv": "conv", **{k: "memory" for k in MEMORY_KINDS}}
TX2_SOURCES = [
    "142 TVM-tuned convolution kernels timed on a Jetson TX2 (GPU and CPU), from the fast-depth project's tuning logs",
    "paper Table 1: paper design paths 1-4 at 6.4/8.0/9.8/12.2 ms; FastDepth 17.1 ms at 224x224; "
    "S2D (ResNet-50) 554.7 ms at 228x304 (TVM, TX2 GPU)",
    "paper Table 3: S2D (ResNet-18) 374.7 ms at 228x912; MonoDepth2 (ResNet-18) 77.26 ms at 192x640",
    "paper: 0.2 J at 6.37 ms (first path), 6.244 J at 554.7 ms (S2D) -> fixed energy + active power",
]
TX2_GPU_NOTES = [
    "fast-depth's pruned FastDepth (5.6 ms; its kernels 4.94 ms) is not fitted: it leaves 0.7 ms for "
    "resizes, adds and launch, where the paper's own figures (FastDepth 17.1 ms, the paper design's "
    "paths, each about twice its kernel time) need several ms; the two setups differ. The paper's "
    "Table 2 FastDepth TX2 row (L_T, L_E) implies about 5.3 ms, i.e. fast-depth's figure, not Table 1's",
    "sparse-to-dense's figures are only met with a very slow transposed convolution (kind deconv, "
    "which no candidate has): TVM's conv2d_transpose on the TX2. Its memory term counts activations "
    "only (weight_traffic: false): with the weights counted too, the ResNet-50 figure (16x the "
    "ResNet-18's deconv weights) and the ResNet-18 one pull it in opposite directions and the best "
    "balance left them at +14.6% and -17.7%",
]


def fit_tx2(data_dir: Path) -> tuple[DeviceProfile, DeviceProfile, dict]:
    """The TX2 GPU on the 71 kernels and every end-to-end figure of the paper; the TX2 CPU on its
    71 kernels and fast-depth's pruned FastDepth figure.

    Memory-bound layers (resize, add, concat, slice) cost a small launch plus the bytes they move at
    their kind's own bandwidth, so they grow with the input as they do on the device; convolutions
    cost a launch plus the longer of MACs at the kind's rate and bytes at the device's bandwidth.
    With figures at 224x224, 228x304, 192x640 and 228x912 the fit can tell fixed costs from ones
    that scale.
    """
    csv = data_dir / "tx2-tvm-kernels" / "kernels.csv"
    gpu, gpu_frames = _fit_tx2_gpu(csv)
    cpu, cpu_kernel_errors = _fit_tx2_cpu(csv)
    return gpu, cpu, {**gpu_frames, "cpu_kernels": cpu_kernel_errors}


def _tx2_energy() -> tuple[float, float]:
    """(fixed J, active W): the line through the paper's (6.37 ms, 0.2 J) and (554.7 ms, 6.244 J)."""
    power = (6.244 - 0.2) / ((554.7 - 6.37) / 1000.0)
    fixed = 0.2 - power * 6.37 / 1000.0
    return fixed, power


def _fit_tx2_gpu(csv: Path) -> tuple[DeviceProfile, dict]:
    """The TX2 GPU profile, fitted on its kernels and the paper's end-to-end figures, and the error
    frames of the kernels, the fitted figures and the held-out check."""
    fixed, power = _tx2_energy()
    gpu_kernels = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(csv, "gpu")]
    gpu_e2e = (_path_observations(4.0, [("paper design", paper_candidate(), PAPER_TX2_PATHS_MS)])
               + _reference_observations(TX2_REFERENCES, 2.0))
    gpu_checks = [_pruned_fastdepth("gpu")]
    base = _start("tx2", "NVIDIA Jetson TX2 GPU (256 Pascal cores), TVM-compiled, batch 1, fp32",
                  True, 150.0, 0.03, 30.0)
    # Transposed convolutions start slow and memory-bound (TVM's conv2d_transpose), else the fit
    # cannot find the direction that explains sparse-to-dense's figures; their weights are reused
    # on chip, so the two S2D decoders (weights 16x apart, activations 1.4x) both fit.
    base = dataclasses.replace(base, energy_fixed_j=fixed, active_power_w=power,
                               kinds={**base.kinds, "deconv": KindCost(2.0, 0.03, 0.05, weight_traffic=False)})
    gpu = fit_profile(base, gpu_kernels + gpu_e2e, TX2_RATE_OF, TX2_OVERHEAD_OF,
                      own_bandwidth=MEMORY_KINDS + ("deconv",))
    k_err, e_err, c_err = errors(gpu, gpu_kernels), errors(gpu, gpu_e2e), errors(gpu, gpu_checks)
    gpu = dataclasses.replace(gpu, provenance={
        "calibrated": True, "sources": list(TX2_SOURCES),
        "fit": [fit_summary(k_err, "71 measured GPU kernels"),
                fit_summary(e_err, "end-to-end figures (paper design paths 1-4, 4 reference networks)")],
        "checks": _check_rows(e_err),
        "not_fitted": _check_rows(c_err) + _scaling_rows(gpu),
        "notes": list(TX2_GPU_NOTES),
        "energy_note": f"E = {fixed:.4f} J + {power:.3f} W x t, through the paper's two figures",
    })
    return gpu, {"gpu_kernels": k_err, "gpu_e2e": e_err, "gpu_checks": c_err}


def _fit_tx2_cpu(csv: Path) -> tuple[DeviceProfile, pd.DataFrame]:
    """The TX2 CPU profile and its kernels' error frame. The kernels fix the convolutions;
    fast-depth's pruned FastDepth at 37 ms end to end (its kernels 27.1 ms) prices what the kernels
    leave out: its resizes and adds, by the bytes they move."""
    cpu_kernels = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(csv, "cpu")]
    cbase = _start("tx2-cpu", "NVIDIA Jetson TX2 CPU (2x Denver2 + 4x Cortex-A57), TVM-compiled, batch 1, fp32",
                   False, 20.0, 0.05, 10.0)
    cpu = fit_profile(cbase, cpu_kernels, TX2_RATE_OF, TX2_OVERHEAD_OF, free_inference=False)
    pruned = _pruned_fastdepth("cpu")
    cpu = _price_memory_kinds(cpu, pruned)
    ck_err, cp_err = errors(cpu, cpu_kernels), errors(cpu, [pruned])
    cpu = dataclasses.replace(cpu, provenance={
        "calibrated": True,
        "sources": [TX2_SOURCES[0],
                    "fast-depth: pruned FastDepth end to end 37 ms on the TX2 CPU, its kernels 27.1 ms"],
        "fit": [fit_summary(ck_err, "71 measured CPU kernels"),
                fit_summary(cp_err, "pruned FastDepth end to end (prices resize/add/concat/slice bytes)")],
        "checks": _check_rows(cp_err),
        "not_fitted": _scaling_rows(cpu),
        "energy_note": "no energy figures for the TX2 CPU: energy is not modelled (0 J)",
    })
    return cpu, ck_err


def _price_memory_kinds(cpu: DeviceProfile, pruned: Observation) -> DeviceProfile:
    """``cpu`` with the memory-bound kinds at the depthwise launch and one bandwidth: the one that
    spends what ``pruned``'s end-to-end time leaves after its other layers. The kernels hold no
    memory-bound layers, so nothing else prices them; no energy figures, no inference overhead."""
    launch = cpu.kinds["depthwise"].overhead_ms
    cpu = dataclasses.replace(
        cpu, inference_overhead_ms=0.0, energy_fixed_j=0.0, active_power_w=0.0,
        kinds={**cpu.kinds, **{k: KindCost(cpu.kinds[k].gmacs, launch) for k in MEMORY_KINDS}})
    memory_layers = [w for w in pruned.workloads if w.kind in MEMORY_KINDS]
    left_ms = pruned.measured_ms - float(cpu.latencies_ms(
        [w for w in pruned.workloads if w.kind not in MEMORY_KINDS]).sum())
    compute_ms = sum(launch + (w.macs / (cpu.kinds[w.kind].gmacs * 1e6) if w.macs else 0.0) for w in memory_layers)
    moved = sum(w.bytes_read + w.bytes_written for w in memory_layers)
    memory_bw = moved / (max(left_ms - compute_ms, 1e-3) * 1e6)
    return dataclasses.replace(cpu, kinds={**cpu.kinds, **{k: KindCost(cpu.kinds[k].gmacs, launch, memory_bw)
                                                           for k in MEMORY_KINDS}})


def _check_rows(frame: pd.DataFrame) -> list[dict]:
    return [{"what": r.what, "target_ms": round(r.measured_ms, 3), "predicted_ms": round(r.predicted_ms, 3),
             "error": round(r.error, 4)} for r in frame.itertuples()]


def rpi4_table2(profile: DeviceProfile) -> dict[str, float]:
    cost = candidate_cost(paper_candidate(), paper_graph=True)   # the graph the paper measured
    out = {}
    for spec in PAPER_RPI4_TABLE2:
        dist = parse_budget(spec)
        out[spec] = anytime_loss(cost.path_costs(profile, dist.kind), PAPER_TABLE1_RMSE, dist)
    return out


def fit_rpi4(tx2_cpu: DeviceProfile) -> DeviceProfile:
    """A Cortex-A72 CPU profile: the TX2 CPU's per-kind efficiencies, scaled by one factor, with an
    energy model, fitted so that the paper design reproduces Table 2's Rpi4 row."""
    base = dataclasses.replace(tx2_cpu, name="rpi4",
                               description="Raspberry Pi 4 (4x Cortex-A72 1.5 GHz), TVM-compiled, batch 1, fp32")

    def make(x: np.ndarray) -> DeviceProfile:
        scale, fixed, power = np.exp(x)
        kinds = {k: dataclasses.replace(v, gmacs=v.gmacs / scale, overhead_ms=v.overhead_ms * scale,
                                        bandwidth_gbs=None if v.bandwidth_gbs is None else v.bandwidth_gbs / scale)
                 for k, v in base.kinds.items()}
        return dataclasses.replace(base, kinds=kinds, bandwidth_gbs=base.bandwidth_gbs / scale,
                                   inference_overhead_ms=base.inference_overhead_ms * scale,
                                   energy_fixed_j=float(fixed), active_power_w=float(power))

    targets = np.array(list(PAPER_RPI4_TABLE2.values()))

    def residuals(x: np.ndarray) -> np.ndarray:
        return np.array(list(rpi4_table2(make(x)).values())) - targets

    best = None
    for s0 in (1.5, 2.5, 4.0):  # the 50/33 ms rows are flat in the scale: try several starts
        r = least_squares(residuals, np.log([s0, 0.1, 4.0]), bounds=(np.log([0.2, 1e-3, 0.5]), np.log([50, 2, 20])))
        if best is None or r.cost < best.cost:
            best = r
    profile = make(best.x)
    table = rpi4_table2(profile)
    mobilenet = Candidate(encoder_blocks=13, ecu=False, decoder_widths=(32,) * 5, exits=(5,))
    mb = candidate_cost(mobilenet)
    mb_ms = float(sum(profile.layer_ms(w) for w in mb.workloads if w.stage == "image_encoder")
                  + profile.inference_overhead_ms)
    return dataclasses.replace(profile, provenance={
        "calibrated": True,
        "sources": ["TX2-CPU per-kind efficiencies (same ARM/TVM toolchain), one speed factor",
                    "paper Table 2, Rpi4 row (L_T@100/50/33 ms, L_E@0.5/0.25 J) with Table 1's RMSEs",
                    "check: MobileNet v1 on a Pi 4, about 72 ms (ncnn, 4 threads)"],
        "fit": [{"what": "Table 2 Rpi4 row", "count": 5,
                 "max_abs_error": round(float(np.max(np.abs(np.array(list(table.values())) - targets))), 4)}],
        "checks": [{"what": k, "target": PAPER_RPI4_TABLE2[k], "predicted": round(v, 4)} for k, v in table.items()]
        + [{"what": "MobileNet v1 encoder (224x224)", "target_ms": MOBILENET_RPI4_MS, "predicted_ms": round(mb_ms, 2)}],
    })


#: Published peak figures (fp32 GFLOP/s, memory GB/s) for scaling uncalibrated estimates.
PEAKS = {
    "tx2": (665.0, 59.7), "jetson-nano": (236.0, 25.6), "orin-nano": (1280.0, 68.0),
    "rpi4": (24.0, 4.0), "rpi5": (60.0, 17.0),
}


def scaled_profile(base: DeviceProfile, name: str, description: str, ref: str) -> DeviceProfile:
    compute = PEAKS[name][0] / PEAKS[ref][0]
    memory = PEAKS[name][1] / PEAKS[ref][1]
    kinds = {k: dataclasses.replace(v, gmacs=v.gmacs * compute,
                                    bandwidth_gbs=None if v.bandwidth_gbs is None else v.bandwidth_gbs * memory)
             for k, v in base.kinds.items()}
    return dataclasses.replace(base, name=name, description=description, kinds=kinds,
                               bandwidth_gbs=base.bandwidth_gbs * memory, provenance={
                                   "calibrated": False,
                                   "sources": [f"uncalibrated estimate: the {ref} profile scaled by published "
                                               f"peak compute ({PEAKS[name][0]:g} vs {PEAKS[ref][0]:g} GFLOP/s fp32) "
                                               f"and memory bandwidth ({PEAKS[name][1]:g} vs {PEAKS[ref][1]:g} GB/s)"],
                                   "fit": [], "checks": []})


def rebuild(data_dir: Path, out_dir: Path = PROFILES_DIR) -> dict:
    gpu, cpu, frames = fit_tx2(data_dir)
    rpi4 = fit_rpi4(cpu)
    profiles = [gpu, cpu, rpi4,
                scaled_profile(gpu, "jetson-nano", "NVIDIA Jetson Nano GPU (128 Maxwell cores)", "tx2"),
                scaled_profile(gpu, "orin-nano", "NVIDIA Jetson Orin Nano GPU (1024 Ampere cores)", "tx2"),
                scaled_profile(rpi4, "rpi5", "Raspberry Pi 5 (4x Cortex-A76 2.4 GHz)", "rpi4")]
    out_dir.mkdir(parents=True, exist_ok=True)
    for p in profiles:
        header = ("# Generated by `python -m explorer.cost.fit`; provenance says what it was fitted on.\n")
        write_atomically(out_dir / f"{p.name}.yaml", header + p.to_yaml())
    return {"profiles": profiles, **frames}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="Rebuild the shipped device profiles from measurements.")
    ap.add_argument("--data", default="../shared/data", help="folder holding tx2-tvm-kernels/")
    ap.add_argument("--out", default=str(PROFILES_DIR))
    args = ap.parse_args(argv)
    res = rebuild(Path(args.data), Path(args.out))
    for p in res["profiles"]:
        print(f"== {p.name}: {p.description}")
        for f in p.provenance.get("fit", []):
            print("   fit  ", f)
        for c in p.provenance.get("checks", []):
            print("   check", c)
        for c in p.provenance.get("not_fitted", []):
            print("   held ", c)


if __name__ == "__main__":
    main()
