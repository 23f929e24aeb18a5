"""An export's ``manifest.json`` as the runtime reads it, checked before any graph is loaded: the
schema (pydantic), stage files confined to the model folder, and each graph's SHA-256 against the one
the export recorded. An edited, truncated or half-replaced export is one line, never a crash inside
onnxruntime."""

from __future__ import annotations

import hashlib
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from explorer.errors import UserError
from explorer.files import read_json, write_json

MANIFEST = "manifest.json"
Side = Annotated[int, Field(gt=0)]


class Stage(BaseModel):
    model_config = ConfigDict(extra="allow")

    file: str = Field(min_length=1)
    path: Optional[int] = None
    sha256: Optional[Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]] = None

    @field_validator("file")
    @classmethod
    def _inside_the_folder(cls, file: str) -> str:
        parts = PurePosixPath(file).parts
        if PurePosixPath(file).is_absolute() or ".." in parts or "\\" in file:
            raise ValueError("a stage file must be a path inside the model folder")
        return file


class Measured(BaseModel):
    """Where an export's ``path_metrics`` come from: the first ``frames`` of a split of ``data``, run at
    ``input_size`` through the exported graphs."""

    data: str
    split: str
    frames: Annotated[int, Field(ge=1)]
    input_size: tuple[Side, Side]
    by: str = "onnxruntime, the exported graphs"


class ExpectedCost(BaseModel):
    latency_ms: list[float]
    energy_j: list[float]
    calibrated: bool


class Manifest(BaseModel):
    """``manifest.json``, the one definition of what an export writes and what the runtime reads (see
    the file formats page). Keys this version does not know are kept (a newer export's additions)."""

    model_config = ConfigDict(extra="allow")

    format: str = Field(pattern=r"^anytime-explorer/1$")
    input_size: tuple[Side, Side]
    scan_row: Annotated[int, Field(ge=0)]
    scan_rows_input: bool = False   # the graphs take each column's scan row (``scan_rows``, (1, W) int64)
    paths: Annotated[int, Field(ge=1)]
    stages: list[Stage] = Field(min_length=1)
    candidate: dict[str, Any]
    candidate_key: Optional[str] = None
    explorer_version: Optional[str] = None
    opset: Optional[int] = None
    architecture: Optional[str] = None
    precision: Literal["fp32", "int8"] = "fp32"
    path_metrics: list[dict[str, float]] = Field(default_factory=list)
    measured: Optional[Measured] = None
    tuned_size: Optional[tuple[Side, Side]] = None
    expected_cost: dict[str, ExpectedCost] = Field(default_factory=dict)
    params: list[float] = Field(default_factory=list)
    macs: list[float] = Field(default_factory=list)
    verification: dict[str, float] = Field(default_factory=dict)
    source: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_figure_per_path(self) -> "Manifest":
        if self.path_metrics and len(self.path_metrics) != self.paths:
            raise ValueError(f"path_metrics has {len(self.path_metrics)} entries for {self.paths} paths")
        return self


def write_manifest(folder: Path, manifest: dict) -> None:
    """Writes ``manifest`` to ``folder`` after checking it against the schema: an export never writes
    a manifest its runtime would refuse."""
    Manifest.model_validate(manifest)
    write_json(Path(folder) / MANIFEST, manifest)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(model_dir: str | Path) -> dict:
    """The manifest of the export in ``model_dir``, checked: schema, scan row inside the image, stage
    files present, inside the folder and (where the export recorded them) with their hashes."""
    folder = Path(model_dir)
    path = folder / MANIFEST
    if not path.is_file():
        raise UserError(f"{folder}: no {MANIFEST} (export a model with `explorer export --out DIR`)")
    data = read_json(path, "export manifest")
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "the file"
        raise UserError(f"{path}: {where}: {first['msg']} (export the model again)") from None
    if manifest.scan_row >= manifest.input_size[0]:
        raise UserError(f"{path}: scan_row {manifest.scan_row} lies outside the {manifest.input_size[0]} image rows")
    root = folder.resolve()
    for stage in manifest.stages:
        f = (folder / stage.file).resolve()
        if root not in f.parents:
            raise UserError(f"{path}: stage file {stage.file} lies outside the model folder")
        if not f.is_file():
            raise UserError(f"{folder / stage.file}: stage graph listed in the manifest is missing")
        if stage.sha256 is not None and file_sha256(f) != stage.sha256:
            raise UserError(f"{folder / stage.file}: the graph does not match the manifest (changed or half "
                            "written): export the model again")
    return data
