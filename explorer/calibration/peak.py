"""This machine's peak multiply-accumulate rate, from its CPU's vector flags, core count and clock,
so that a measured graph can be quoted as a fraction of what the silicon could do.

    peak = cores x GHz x FMA units per core x MAC lanes per FMA instruction

fp32 lanes: 16 with AVX-512, 8 with AVX2+FMA, 4 with SSE or NEON. int8 lanes are 4x the fp32 ones
where the CPU has dot-product instructions (AVX-512 VNNI, AVX-VNNI, ARM dotprod), else 2x (16-bit
multiply-add). FMA units per core cannot be read from the flags: 2 is assumed for AVX-512 and
AVX2 server cores (Skylake-SP Gold/Platinum and later, Zen), 1 for the rest, and 1 for AMD's Zen 4
(family 25 with AVX-512), whose two FMA units are 256 bits wide and take a 512-bit FMA together;
``fma_units`` overrides it. The clock is the highest one the kernel reports (cpufreq's maximum, the
model name's "@ x GHz", then /proc/cpuinfo's current MHz). A virtual machine often reports only its base clock, below the
one its cores boost to: ``gemm_gmacs`` measures what a large matrix product actually reaches.
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from explorer.deploy.sessions import session
from explorer.probe import time_call


@dataclass(frozen=True)
class HostPeak:
    cores: int
    ghz: float
    fma_units: int
    fp32_lanes: int
    int8_lanes: int
    isa: str              # the widest vector extension found
    clock_source: str     # where ``ghz`` came from

    @property
    def fp32_gmacs(self) -> float:
        return self.cores * self.ghz * self.fma_units * self.fp32_lanes

    @property
    def int8_gmacs(self) -> float:
        return self.cores * self.ghz * self.fma_units * self.int8_lanes

    def fraction(self, macs: float, ms: float, precision: str = "fp32") -> float:
        """The share of this peak that ``macs`` multiply-accumulates in ``ms`` milliseconds reach."""
        peak = self.int8_gmacs if precision == "int8" else self.fp32_gmacs
        return macs / (ms * 1e6) / peak

    def describe(self) -> str:
        return (f"{self.cores} cores x {self.ghz:.2f} GHz ({self.clock_source}) x {self.fma_units} FMA units x "
                f"{self.fp32_lanes} fp32 lanes ({self.isa}) = {self.fp32_gmacs:.0f} GMAC/s fp32, "
                f"{self.int8_gmacs:.0f} GMAC/s int8")

    def to_dict(self) -> dict:
        return {**asdict(self), "fp32_gmacs": round(self.fp32_gmacs, 1), "int8_gmacs": round(self.int8_gmacs, 1)}


def _clock_ghz(cpuinfo: str, sysfs: Path) -> tuple[float, str]:
    max_freq = sysfs / "cpu0" / "cpufreq" / "cpuinfo_max_freq"
    if max_freq.is_file():
        try:
            return int(max_freq.read_text().strip()) / 1e6, "cpufreq maximum"
        except ValueError:
            pass
    model = re.search(r"^model name\s*:.*@\s*([\d.]+)\s*GHz", cpuinfo, re.M)
    if model:
        return float(model.group(1)), "model name"
    mhz = [float(m) for m in re.findall(r"^cpu MHz\s*:\s*([\d.]+)", cpuinfo, re.M)]
    if mhz:
        return max(mhz) / 1000, "current clock"
    return 1.0, "unknown (1 GHz assumed)"


def host_peak(cpuinfo: str | None = None, sysfs: str | Path = "/sys/devices/system/cpu",
              cores: int | None = None, fma_units: int | None = None) -> HostPeak:
    """This machine's peak (or, for tests, the one ``cpuinfo`` and ``sysfs`` describe)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    flags_line = re.search(r"^(?:flags|Features)\s*:(.*)$", cpuinfo, re.M)
    flags = set(flags_line.group(1).split()) if flags_line else set()
    amd_family = re.search(r"^cpu family\s*:\s*(\d+)", cpuinfo, re.M) if "AuthenticAMD" in cpuinfo else None
    if "avx512f" in flags and amd_family and int(amd_family.group(1)) == 25:
        isa, lanes, units = "AVX-512 on 256-bit units", 16, 1
    elif "avx512f" in flags:
        isa, lanes, units = "AVX-512", 16, 2
    elif "avx2" in flags and "fma" in flags:
        isa, lanes, units = "AVX2+FMA", 8, 2
    elif flags & {"asimd", "neon"}:
        isa, lanes, units = "NEON", 4, 1
    else:
        isa, lanes, units = "SSE", 4, 1
    dot = bool(flags & {"avx512_vnni", "avx_vnni", "asimddp", "amx_int8"})
    ghz, source = _clock_ghz(cpuinfo, Path(sysfs))
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return HostPeak(cores=cores, ghz=ghz, fma_units=fma_units or units, fp32_lanes=lanes,
                    int8_lanes=lanes * (4 if dot else 2), isa=isa + (" + int8 dot product" if dot else ""),
                    clock_source=source)


def gemm_gmacs(n: int = 1024, reps: int = 5) -> list[float]:
    """The fp32 rate one n x n x n matrix product reaches here in onnxruntime (its MLAS kernels, the
    ones its convolutions use), in GMAC/s, one figure per rep (the median of 5 products): an
    attainable ceiling to set beside the nominal peak."""
    import numpy as np
    from onnx import TensorProto, helper


    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "gemm",
                              [helper.make_tensor_value_info(k, TensorProto.FLOAT, [n, n]) for k in "ab"],
                              [helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])])
    # opset 13's IR version: onnx's newest may be past what the installed onnxruntime reads
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=7)
    sess = session(model.SerializeToString())   # as every measured graph: the same threads and pool
    rng = np.random.default_rng(0)
    feeds = {k: rng.standard_normal((n, n), dtype=np.float32) for k in "ab"}
    return [n ** 3 / (time_call(lambda: sess.run(None, feeds), 1, 5) * 1e6) for _ in range(reps)]
