"""Device profiles: data (YAML) that turn workloads into latency and energy.

Per layer kind, a profile has an effective compute rate (GMAC/s) and a fixed per-layer cost (ms);
one memory bandwidth (GB/s) prices bytes moved, or the kind's own where it has one: memory-bound
kinds (resize, add, concat, slice) are priced by the bytes they move at their own rate, so their
cost grows with the tensors as on the device. On a GPU-like device compute and memory overlap
(a layer takes the longer of the two), on a CPU-like one they add. A run also pays a fixed
``inference_overhead_ms`` before its first stage. Energy is a fixed energy per inference plus
active power times time. ``provenance`` records what a profile was fitted on and its error there.
A profile may also price int8 graphs (statically quantized, as ``explorer export --quantize int8``
writes them): its ``int8`` section holds their own kinds, bandwidth and overheads (what it leaves
out is the fp32 one's), fitted by ``explorer calibrate`` on quantized layer and stage graphs. Such an
export quantizes each stage graph whole and keeps it int8 only where that runs faster
(``explorer.deploy.quantize``), so an int8 candidate's path times take, per deployed stage graph, the int8
price where it is at most ``INT8_KEEP_RATIO`` of the fp32 one, else the fp32 price.

Built-in profiles live in ``explorer/cost/profiles/*.yaml``; any YAML file with the same fields
can be passed wherever a device name is accepted (``--device ./mybox.yaml``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import yaml

from explorer.cost.workloads import ALL_KINDS, BYTES_PER_VALUE, KINDS, OPTIONAL_KINDS, Workload
from explorer.errors import UserError
from explorer.files import read_yaml
from explorer.cost.precision import FLOAT_STAGES, INT8_KEEP_RATIO

PROFILES_DIR = Path(__file__).resolve().parent / "profiles"

#: Where a profile's latency or energy comes from (``provenance.latency`` / ``provenance.energy``).
BASES = ("measured", "published", "estimate")


@dataclass(frozen=True)
class KindCost:
    gmacs: float = 1.0          # effective compute rate, GMAC/s
    overhead_ms: float = 0.0    # fixed cost per layer of this kind
    bandwidth_gbs: float | None = None  # this kind's own memory rate (else the profile's)
    # False: weights are staged on chip and reused, so the memory term counts activations only
    weight_traffic: bool = True


@dataclass(frozen=True)
class DeviceProfile:
    name: str
    description: str
    overlap: bool
    bandwidth_gbs: float
    kinds: dict[str, KindCost]
    inference_overhead_ms: float = 0.0
    stage_overhead_ms: float = 0.0
    # A layer's time past its overhead is (its compute or memory time in ms) ** body_exponent; above 1
    # where bigger tensors run less efficiently (out of cache), as `explorer calibrate` finds on a CPU.
    body_exponent: float = 1.0
    energy_fixed_j: float = 0.0
    active_power_w: float = 0.0
    provenance: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    int8: "DeviceProfile | None" = None     # the same device running int8 graphs, where measured
    # set on an ``int8`` section: the fp32 profile, which prices the stage graphs an int8 export keeps fp32
    float_layers: "DeviceProfile | None" = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        missing = {k: self.kinds[f] for k, f in OPTIONAL_KINDS.items() if k not in self.kinds and f in self.kinds}
        if missing:  # an optional kind the profile does not price costs what its fallback costs
            object.__setattr__(self, "kinds", {**self.kinds, **missing})
        if self.int8 is not None and self.int8.float_layers is not self:
            object.__setattr__(self, "int8", replace(self.int8, float_layers=self))

    # -- precision -----------------------------------------------------------------------------
    @property
    def precisions(self) -> tuple[str, ...]:
        return ("fp32", "int8") if self.int8 is not None else ("fp32",)

    def at_precision(self, precision: str) -> "DeviceProfile":
        """The profile that prices graphs of ``precision`` ('fp32' or 'int8') on this device."""
        if precision == "fp32":
            return self
        if precision == "int8" and self.int8 is not None:
            return self.int8
        if precision == "int8":
            raise UserError(f"the {self.name} profile prices no int8 graphs: measure a profile that does "
                            "(`explorer calibrate --out mybox.yaml` times int8 layers too) or keep precision fp32")
        raise UserError(f"unknown precision '{precision}': use fp32 or int8")

    # -- prediction ----------------------------------------------------------------------------
    def layer_ms(self, w: Workload) -> float:
        k = self.kinds[w.kind]
        compute = w.macs / (k.gmacs * 1e6) if w.macs else 0.0
        moved = w.bytes_read + w.bytes_written
        if not k.weight_traffic:
            moved = max(moved - w.params * BYTES_PER_VALUE, w.bytes_written)
        memory = moved / ((k.bandwidth_gbs or self.bandwidth_gbs) * 1e6)
        body = max(compute, memory) if self.overlap else compute + memory
        return k.overhead_ms + (body if self.body_exponent == 1.0 else body ** self.body_exponent)

    def latencies_ms(self, workloads: Iterable[Workload]) -> np.ndarray:
        return np.array([self.layer_ms(w) for w in workloads])

    def energy_j(self, latency_ms: float | np.ndarray) -> float | np.ndarray:
        """Energy of a run that lasted ``latency_ms`` (0 ms = nothing ran = 0 J)."""
        t = np.asarray(latency_ms, dtype=float)
        e = np.where(t > 0, self.energy_fixed_j + self.active_power_w * t / 1000.0, 0.0)
        return float(e) if e.ndim == 0 else e

    @property
    def calibrated(self) -> bool:
        return bool(self.provenance.get("calibrated", False))

    @property
    def latency_basis(self) -> str:
        """'measured' (on the device), 'published' (fitted to published figures) or 'estimate'."""
        said = self.provenance.get("latency")
        if said in BASES:
            return said
        if not self.calibrated:
            return "estimate"
        sources = " ".join(map(str, self.provenance.get("sources") or []))
        return "measured" if "explorer calibrate" in sources else "published"

    @property
    def energy_basis(self) -> str:
        """As ``latency_basis``, or 'none' when the profile prices no energy."""
        said = self.provenance.get("energy")
        if said in BASES:
            return said
        if self.energy_fixed_j == 0 and self.active_power_w == 0:
            return "none"
        if not self.calibrated or "estimate" in str(self.provenance.get("energy_note", "")):
            return "estimate"
        return "published"

    # -- (de)serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "description": self.description,
            "overlap": self.overlap,
            "bandwidth_gbs": _round(self.bandwidth_gbs),
            "inference_overhead_ms": _round(self.inference_overhead_ms),
            "stage_overhead_ms": _round(self.stage_overhead_ms),
            **({} if self.body_exponent == 1.0 else {"body_exponent": _round(self.body_exponent)}),
            "kinds": {k: {"gmacs": _round(v.gmacs), "overhead_ms": _round(v.overhead_ms),
                          **({"bandwidth_gbs": _round(v.bandwidth_gbs)} if v.bandwidth_gbs else {}),
                          **({} if v.weight_traffic else {"weight_traffic": False})}
                      for k, v in self.kinds.items()},
            "energy": {"fixed_j": _round(self.energy_fixed_j), "active_power_w": _round(self.active_power_w)},
            "provenance": self.provenance,
            **({"int8": self._int8_dict()} if self.int8 is not None else {}),
        }

    def _int8_dict(self) -> dict[str, Any]:
        d = self.int8.to_dict()
        return {k: d[k] for k in ("overlap", "bandwidth_gbs", "inference_overhead_ms", "stage_overhead_ms",
                                  "body_exponent", "kinds", "provenance") if k in d}

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, width=100)

    @classmethod
    def from_dict(cls, data: Any, source: str) -> "DeviceProfile":
        if not isinstance(data, dict):
            raise UserError(f"{source}: a device profile is a YAML mapping")
        required = ("name", "overlap", "bandwidth_gbs", "kinds")
        missing = [k for k in required if k not in data]
        if missing:
            raise UserError(f"{source}: device profile lacks {missing}")
        known = set(required) | {"description", "inference_overhead_ms", "stage_overhead_ms", "body_exponent", "energy",
                                 "provenance", "int8"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise UserError(f"{source}: unknown device profile key(s) {unknown}; known: {sorted(known)}")
        kinds_raw = data["kinds"]
        if not isinstance(kinds_raw, dict):
            raise UserError(f"{source}: 'kinds' must map layer kinds {list(KINDS)} to gmacs/overhead_ms")
        lacking = [k for k in KINDS if k not in kinds_raw]
        if lacking:
            raise UserError(f"{source}: 'kinds' lacks {lacking}: a profile must price every layer kind {list(KINDS)}")
        kinds = {}
        for k, v in kinds_raw.items():
            if k not in ALL_KINDS:
                raise UserError(f"{source}: unknown layer kind '{k}'; kinds are {list(ALL_KINDS)}")
            if not isinstance(v, dict) or set(v) - {"gmacs", "overhead_ms", "bandwidth_gbs", "weight_traffic"}:
                raise UserError(f"{source}: kinds.{k} must be a mapping with gmacs, overhead_ms "
                                "and optionally bandwidth_gbs and weight_traffic")
            bw = v.get("bandwidth_gbs")
            kinds[k] = KindCost(_positive(v.get("gmacs", 1.0), f"{source}: kinds.{k}.gmacs"),
                                _nonneg(v.get("overhead_ms", 0.0), f"{source}: kinds.{k}.overhead_ms"),
                                None if bw is None else _positive(bw, f"{source}: kinds.{k}.bandwidth_gbs"),
                                _bool(v.get("weight_traffic", True), f"{source}: kinds.{k}.weight_traffic"))
        energy = data.get("energy") or {}
        if not isinstance(energy, dict):
            raise UserError(f"{source}: 'energy' must be a mapping with fixed_j and active_power_w")
        unknown = sorted(set(energy) - {"fixed_j", "active_power_w"})
        if unknown:   # a misspelt key would price energy at 0 in silence
            raise UserError(f"{source}: unknown key(s) under 'energy': {unknown} (it takes fixed_j and active_power_w)")
        int8 = data.get("int8")
        if int8 is not None:
            if not isinstance(int8, dict) or "kinds" not in int8:
                raise UserError(f"{source}: 'int8' must be a mapping with its own 'kinds' (and optionally overlap, "
                                "bandwidth_gbs, inference_overhead_ms, stage_overhead_ms)")
            inherited = {k: data[k] for k in ("name", "description", "overlap", "bandwidth_gbs", "energy",
                                              "inference_overhead_ms", "stage_overhead_ms") if k in data}
            int8 = cls.from_dict({**inherited, **int8}, f"{source} (int8)")
        return cls(
            int8=int8,
            name=str(data["name"]), description=str(data.get("description", "")),
            overlap=_bool(data["overlap"], f"{source}: overlap"),
            bandwidth_gbs=_positive(data["bandwidth_gbs"], f"{source}: bandwidth_gbs"),
            kinds=kinds,
            inference_overhead_ms=_nonneg(data.get("inference_overhead_ms", 0.0), f"{source}: inference_overhead_ms"),
            stage_overhead_ms=_nonneg(data.get("stage_overhead_ms", 0.0), f"{source}: stage_overhead_ms"),
            body_exponent=_body_exponent(data.get("body_exponent", 1.0), f"{source}: body_exponent"),
            energy_fixed_j=_nonneg(energy.get("fixed_j", 0.0), f"{source}: energy.fixed_j"),
            active_power_w=_nonneg(energy.get("active_power_w", 0.0), f"{source}: energy.active_power_w"),
            provenance=data.get("provenance") or {}, source=source)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "DeviceProfile":
        p = Path(path)
        data = read_yaml(p, "device profile (YAML)")
        return cls.from_dict(data, str(p))


def check_budget_priced(profile: DeviceProfile, budget) -> None:
    """An energy budget needs a profile that prices energy: on one that does not, every path would cost
    0 J and the anytime loss would say nothing. ``budget``: a parsed budget distribution."""
    if budget.kind == "energy" and profile.energy_fixed_j == 0 and profile.active_power_w == 0:
        raise UserError(f"device profile {profile.name} prices no energy, so an energy budget ({budget.spec}) "
                        "cannot rank anything: give a time budget, or a profile with energy figures "
                        "(explorer devices)")


def _round(x: float) -> float:
    return float(f"{x:.6g}")


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise UserError(f"{where} must be a finite number, got {v!r}")
    return float(v)


#: the body exponents a profile may hold: explorer calibrate fits 0.95 to 1.2; far outside, a layer's
#: time would be its body's square or root (or its millionth power)
BODY_EXPONENT_RANGE = (0.5, 2.0)


def _body_exponent(v: Any, where: str) -> float:
    x = _number(v, where)
    low, high = BODY_EXPONENT_RANGE
    if not low <= x <= high:
        raise UserError(f"{where} must lie in [{low}, {high}] (explorer calibrate fits 0.95 to 1.2), got {x}")
    return x


def _positive(v: Any, where: str) -> float:
    x = _number(v, where)
    if not x > 0:
        raise UserError(f"{where} must be positive, got {x}")
    return x


def _nonneg(v: Any, where: str) -> float:
    x = _number(v, where)
    if x < 0:
        raise UserError(f"{where} must not be negative, got {x}")
    return x


def _bool(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise UserError(f"{where} must be true or false, got {v!r}")
    return v


# -- registry ------------------------------------------------------------------------------------
def available_devices() -> list[str]:
    """Names of the built-in profiles (plus 'host', measured on this machine)."""
    return sorted(p.stem for p in PROFILES_DIR.glob("*.yaml"))


def get_device(spec: str | Path | DeviceProfile) -> DeviceProfile:
    """A built-in profile by name, or a profile file by path."""
    if isinstance(spec, DeviceProfile):
        return spec
    text = str(spec)
    if not text.strip():   # an unset shell variable: never "no device" in silence
        raise UserError(f"--device is empty: give one of {available_devices()} or a profile YAML file")
    builtin = PROFILES_DIR / f"{text}.yaml"
    if builtin.is_file():
        return DeviceProfile.from_yaml(builtin)
    if text.endswith((".yaml", ".yml")) or "/" in text:
        if not Path(text).is_file():
            raise UserError(f"device profile {text}: no such file")
        return DeviceProfile.from_yaml(text)
    raise UserError(f"unknown device '{text}': use one of {available_devices()} or a profile YAML file "
                    "(make one with `explorer calibrate --out mybox.yaml`)")


def path_latencies_ms(profile: DeviceProfile, workloads: Sequence[Workload],
                      path_stages: Sequence[Sequence[str]]) -> list[float]:
    """Latency at which each path is ready: the inference overhead plus every stage up to its exit
    (each stage paying its own launch cost, ``stage_overhead_ms``).

    ``path_stages[i]`` lists the stages that path i+1 needs (a prefix of the execution order). On an
    int8 section, each deployed stage graph (the stages between two exits) costs what an int8 export
    runs it at: its int8 price where that is at most ``INT8_KEEP_RATIO`` of its fp32 price, else fp32.
    """
    per_stage = _stage_ms(profile, workloads)
    if profile.float_layers is not None:
        fp32 = _stage_ms(profile.float_layers, workloads)
        per_stage = _int8_stage_ms(per_stage, fp32)
        for graph, int8 in zip(deployed_graphs(path_stages), int8_graphs(profile, workloads, path_stages)):
            if not int8:
                per_stage.update({s: fp32.get(s, 0.0) for s in graph})
    return [profile.inference_overhead_ms
            + sum(per_stage.get(s, 0.0) + profile.stage_overhead_ms for s in stages)
            for stages in path_stages]


def deployed_graphs(path_stages: Sequence[Sequence[str]]) -> list[list[str]]:
    """The stages of each deployed stage graph (those between two exits), in order."""
    out, done = [], 0
    for stages in path_stages:
        out.append(list(stages)[done:])
        done = len(stages)
    return out


def int8_graphs(profile: DeviceProfile, workloads: Sequence[Workload],
                path_stages: Sequence[Sequence[str]]) -> list[bool]:
    """Per deployed stage graph, whether an int8 export keeps it int8 on this device: its price on
    ``profile`` (an int8 section) is at most ``INT8_KEEP_RATIO`` of its fp32 price."""
    fp32 = _stage_ms(profile.float_layers or profile, workloads)
    int8 = _int8_stage_ms(_stage_ms(profile, workloads), fp32)
    return [sum(int8.get(s, 0.0) for s in graph) <= INT8_KEEP_RATIO * sum(fp32.get(s, 0.0) for s in graph)
            for graph in deployed_graphs(path_stages)]


def _int8_stage_ms(int8: dict[str, float], fp32: dict[str, float]) -> dict[str, float]:
    """Per-stage times of an int8 graph: the stages it keeps fp32 (``FLOAT_STAGES``) at their fp32 price."""
    return {s: fp32.get(s, ms) if s in FLOAT_STAGES else ms for s, ms in int8.items()}


def _stage_ms(profile: DeviceProfile, workloads: Sequence[Workload]) -> dict[str, float]:
    per_stage: dict[str, float] = {}
    for w, t in zip(workloads, profile.latencies_ms(workloads)):
        per_stage[w.stage] = per_stage.get(w.stage, 0.0) + float(t)
    return per_stage
