"""The probe results file as the fit reads it, checked whole before anything is fitted: one schema
(pydantic) that also documents the format. A results file edited by hand or truncated becomes one
line naming the file and the first key that is wrong; never a traceback.

The probe itself (``explorer.probe``) runs with numpy and onnxruntime only, so it checks just the
file's format and version; everything below is checked where the fit runs."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from explorer.cost.workloads import Workload
from explorer.errors import UserError

#: a timing in milliseconds: positive and finite
Ms = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Count = Annotated[int, Field(gt=0)]


class _Open(BaseModel):
    """Keys the fit does not read are kept: newer probes may write more."""

    model_config = ConfigDict(extra="allow")


class LayerEntry(_Open):
    id: str = Field(min_length=1)
    workload: dict[str, Any]
    precision: Literal["fp32", "int8"] = "fp32"

    @field_validator("workload")
    @classmethod
    def _a_workload(cls, w: dict[str, Any]) -> dict[str, Any]:
        try:
            wl = Workload(**{**w, "in_shape": tuple(w["in_shape"]), "out_shape": tuple(w["out_shape"])})
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a layer workload ({type(exc).__name__}: {exc})") from None
        if not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0
                   for v in (wl.macs, wl.params, wl.bytes_read, wl.bytes_written)):
            raise ValueError("a workload's MACs, parameters and bytes must be finite and non-negative")
        return w


class CandidateEntry(_Open):
    key: str = Field(min_length=1)
    candidate: dict[str, Any]
    input_size: Optional[tuple[Count, Count]] = None
    precision: Literal["fp32", "int8"] = "fp32"


class Bundle(_Open):
    id: str = Field(min_length=1)
    input_size: tuple[Count, Count]
    layers: list[LayerEntry] = Field(min_length=1)
    candidates: list[CandidateEntry]


class Device(_Open):
    onnxruntime: str
    machine: str
    cpu: str
    cores: Optional[Count] = None
    board: str = ""
    host: str = ""


class Conditions(_Open):
    provider: str = Field(min_length=1)
    threads: Count
    repeats: Count
    warmup: Annotated[int, Field(ge=0)]
    statistic: str
    thread_pool: str = "per-session"


class ProbeResults(_Open):
    format: Literal["explorer-probe-results"]
    version: Literal[1]
    bundle: Bundle
    device: Device
    conditions: Conditions
    layers: dict[str, Ms]
    stages: dict[str, dict[str, Ms]]
    energy: Optional[dict[str, Any]] = None
    speed: Optional[dict[str, Any]] = None


def check_results(data: Any, path: str | Path) -> dict:
    """``data`` (a parsed results file) if it holds what the fit reads, else a UserError naming the
    first wrong key."""
    try:
        ProbeResults.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "the file"
        raise UserError(f"{path}: {where}: {first['msg']} (run the probe again, or restore the file it wrote)") \
            from None
    return data
