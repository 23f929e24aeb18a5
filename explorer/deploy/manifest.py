"""An export's ``manifest.json``, typed (:class:`Manifest`): the one module that names its keys. The
export builds a ``Manifest`` and writes it (:func:`write_manifest`); the runtime and every other reader
get one from :func:`read_manifest`, checked before any graph is loaded: the schema (pydantic), stage
files confined to the model folder, and each graph's SHA-256 against the one the export recorded. An
edited, truncated or half-replaced export is one line, never a crash inside onnxruntime."""

from __future__ import annotations

import hashlib
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from explorer.errors import UserError
from explorer.files import read_json, write_json

MANIFEST = "manifest.json"
#: the validation frames an export carries for ``explorer curve`` (:class:`CurveFrames`)
CURVE_FRAMES = "curve_frames.npz"
Side = Annotated[int, Field(gt=0)]
Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]


def _inside_the_folder(file: str, what: str) -> str:
    parts = PurePosixPath(file).parts
    if PurePosixPath(file).is_absolute() or ".." in parts or "\\" in file:
        raise ValueError(f"{what} must be a path inside the model folder")
    return file


#: per path, one figure per metric name (``rmse``, ``delta1``, ``photometric``, ...), path 0 first
PathMetrics = list[dict[str, float]]


class StageTiming(BaseModel):
    """``ms_here``: a stage graph's median time on the exporting machine in the staged chain, fp32 and
    int8, and the whole chain's with it in each precision."""

    model_config = ConfigDict(extra="allow")

    fp32: float
    int8: float
    staged_fp32: float
    staged_int8: float


class Stage(BaseModel):
    """One stage graph of the export, in execution order."""

    model_config = ConfigDict(extra="allow")

    file: str = Field(min_length=1)
    name: str = ""                         # the stages it runs, joined by '+' (``path0``: path 0's graph)
    stages: list[str] = Field(default_factory=list)
    inputs: list[str] = Field(default_factory=list)
    outputs: list[str] = Field(default_factory=list)
    path: Optional[int] = None             # the path it completes
    precision: Optional[Literal["fp32", "int8"]] = None   # int8 exports: this graph's
    ms_here: Optional[StageTiming] = None
    sha256: Optional[Sha256] = None

    @field_validator("file")
    @classmethod
    def _inside_the_folder(cls, file: str) -> str:
        return _inside_the_folder(file, "a stage file")

    @property
    def is_scan_path(self) -> bool:
        """Path 0's graph: the interpolated scan, read by no later stage."""
        return self.path == 0 and list(self.outputs) == ["depth_0"]


class Measured(BaseModel):
    """Where an export's ``path_metrics`` come from: the first ``frames`` of a split of ``data``, run at
    ``input_size`` through the exported graphs."""

    model_config = ConfigDict(extra="allow")

    data: str
    split: str
    frames: Annotated[int, Field(ge=1)]
    input_size: tuple[Side, Side]
    by: str = "onnxruntime, the exported graphs"


class CurveFrames(BaseModel):
    """``curve_frames``: the first ``frames`` validation frames of ``data`` that ``explorer curve`` measures
    on where no data set can be read (the runtime install), in ``file`` (an ``.npz``: ``image``, ``scan``,
    ``depth`` and, where the graphs take them, ``scan_rows``, one row per frame, each as the graphs take
    it at the export's input size), checked against ``sha256`` when read."""

    model_config = ConfigDict(extra="allow")

    file: str = Field(min_length=1)
    data: str
    split: str = "val"
    frames: Annotated[int, Field(ge=1)]
    sha256: Sha256

    @field_validator("file")
    @classmethod
    def _inside_the_folder(cls, file: str) -> str:
        return _inside_the_folder(file, "the curve frames file")


class ExpectedCost(BaseModel):
    """What a device profile predicts per path (cumulative), and whether the profile was calibrated."""

    model_config = ConfigDict(extra="allow")

    latency_ms: list[float]
    energy_j: list[float]
    calibrated: bool


class Verification(BaseModel):
    """The largest |onnxruntime - PyTorch| over every path's map on a random input, and the tolerance."""

    model_config = ConfigDict(extra="allow")

    max_abs_diff: float
    tolerance: float


class Source(BaseModel):
    """Where the weights came from: a study's trial or a checkpoint; a study's own per-path figures only
    where it measured them at the size exported."""

    model_config = ConfigDict(extra="allow")

    study: Optional[str] = None
    trial: Optional[int] = None
    objective: Optional[float] = None
    figures: Optional[str] = None
    study_path_metrics: Optional[list[dict[str, Any]]] = None
    study_measured: Optional[dict[str, Any]] = None
    checkpoint: Optional[str] = None
    trained_candidate: Optional[dict[str, Any]] = None   # where exits were left out of what ships: as trained
    dropped_exits: Optional[list[dict[str, Any]]] = None  # each exit left out, with the error that left it out


class Frames(BaseModel):
    """Frames of a data set an int8 export was calibrated or evaluated on."""

    model_config = ConfigDict(extra="allow")

    data: str
    split: str
    frames: int


class QuantizationRecord(BaseModel):
    """``quantization`` of an int8 export: how its graphs were quantized and what that cost each path."""

    model_config = ConfigDict(extra="allow")

    method: str = ""
    int8_stages: str = ""
    calibration: Optional[Frames] = None
    evaluation: Optional[Frames] = None
    rmse_degradation: list[float] = Field(default_factory=list)
    max_degradation: Optional[float] = None
    forced: bool = False
    quantized_graphs: list[str] = Field(default_factory=list)
    kept_fp32_for_accuracy: list[str] = Field(default_factory=list)


class Manifest(BaseModel):
    """``manifest.json``, the one definition of what an export writes and what the runtime reads (see
    the file formats page). Keys this version does not know are kept (a newer export's additions), and
    a manifest is written with the keys it was given or read with (``write_manifest``)."""

    model_config = ConfigDict(extra="allow")

    format: str = Field(pattern=r"^anytime-explorer/1$")
    explorer_version: Optional[str] = None
    opset: Optional[int] = None
    candidate: dict[str, Any]              # as in candidate YAML (``Candidate.from_dict``)
    candidate_key: Optional[str] = None
    architecture: Optional[str] = None
    input_size: tuple[Side, Side]
    scan_row: Annotated[int, Field(ge=0)]
    image: Optional[str] = None            # what the inputs are, in words
    scan: Optional[str] = None
    scan_rows_input: bool = False   # the graphs take each column's scan row (``scan_rows``, (1, W) int64)
    stages: list[Stage] = Field(min_length=1)
    paths: Annotated[int, Field(ge=1)]
    path_metrics: PathMetrics = Field(default_factory=list)
    expected_cost: dict[str, ExpectedCost] = Field(default_factory=dict)
    expected_cost_precision: Optional[str] = None
    params: list[Union[int, float]] = Field(default_factory=list)
    macs: list[Union[int, float]] = Field(default_factory=list)
    verification: Optional[Verification] = None
    source: Source = Field(default_factory=Source)
    precision: Literal["fp32", "int8"] = "fp32"
    tuned_size: Optional[tuple[Side, Side]] = None
    measured: Optional[Measured] = None
    curve_frames: Optional[CurveFrames] = None   # none where the frames measured had no depth
    # int8 exports: the paths before and after quantization (``path_metrics`` is then the int8 one and
    # ``path_metrics_trained`` the fp32 graphs', on the same frames)
    path_metrics_fp32: Optional[PathMetrics] = None
    path_metrics_int8: Optional[PathMetrics] = None
    quantization: Optional[QuantizationRecord] = None
    path_metrics_trained: Optional[PathMetrics] = None
    expected_cost_note: Optional[str] = None

    @model_validator(mode="after")
    def _one_figure_per_path(self) -> "Manifest":
        if self.path_metrics and len(self.path_metrics) != self.paths:
            raise ValueError(f"path_metrics has {len(self.path_metrics)} entries for {self.paths} paths")
        return self

    def to_json(self) -> dict:
        """What ``manifest.json`` holds: the keys given or read (none added at their defaults), and the
        keys this version does not know."""
        return self.model_dump(mode="json", exclude_unset=True)


def write_manifest(folder: Path, manifest: Manifest) -> None:
    """Writes ``manifest`` to ``folder`` after checking what it writes against the schema (a field set
    after the manifest was made included): an export never writes a manifest its runtime would refuse."""
    data = manifest.to_json()
    Manifest.model_validate(data)
    write_json(Path(folder) / MANIFEST, data)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(model_dir: str | Path) -> Manifest:
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
    return manifest


def curve_frames_file(model_dir: str | Path, manifest: Manifest) -> Path:
    """The file of the curve frames ``manifest`` names, checked as stage files are: inside the folder,
    present, and with the SHA-256 the export recorded."""
    folder = Path(model_dir)
    entry = manifest.curve_frames
    if entry is None:
        raise UserError(f"{folder / MANIFEST}: names no curve frames")
    f = (folder / entry.file).resolve()
    if folder.resolve() not in f.parents:
        raise UserError(f"{folder / MANIFEST}: curve frames file {entry.file} lies outside the model folder")
    if not f.is_file():
        raise UserError(f"{folder / entry.file}: curve frames listed in the manifest are missing: export the model "
                        "again")
    if file_sha256(f) != entry.sha256:
        raise UserError(f"{folder / entry.file}: the curve frames do not match the manifest (changed or half "
                        "written): export the model again")
    return f
