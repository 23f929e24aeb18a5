"""Data specs: the one string that names a data set (``KIND[:PATH or counts][,KEY=VALUE...]``),
parsed and checked once, at the edge, and written back canonically (it is part of a study's identity
and of a supernet's cache key).

Options after the path, comma-separated:

- a LiDAR model (:data:`explorer.scan.LIDAR_KEYS`: ``fov``, ``resolution``, ``noise``,
  ``dropout``, ``height``, ``tilt``, ...): the scan simulated from the depth where the data has no
  real scan, or the mount of a real scan where the data does not give it;
- ``val=``: the validation share (``0.2``) of a source without a split of its own, or for a CSV of
  pairs a CSV of its own (``nyu:train.csv,val=val.csv``);
- for ROS bags, the topics and the pairing tolerance (:mod:`explorer.data.rosbag`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from explorer.scan import LIDAR_KEYS, RADIAN_KEYS, LidarModel, lidar_model, rigid_transform
from explorer.data.splits import parse_share
from explorer.errors import UserError

SPEC_HELP = ("data specs: synthetic, synthetic:TRAIN:VAL, nyu:PATH (h5 folder or CSV), kitti:PATH, rosbag:BAG; "
             "sequences: synthetic-seq[:TRAIN:VAL], kitti-seq:DRIVE, frames:FOLDER, rosbag-seq:BAG; "
             "options after a comma, e.g. synthetic,tilt=2,resolution=0.5 or nyu:pairs.csv,val=0.2")
SEQUENCE_KINDS = ("synthetic-seq", "kitti-seq", "frames", "rosbag-seq")
PATH_KINDS = ("nyu", "kitti", "kitti-seq", "frames", "rosbag", "rosbag-seq")
GENERATED_DEFAULTS = {"synthetic": (2000, 200), "synthetic-seq": (1200, 120)}
#: kinds whose scan is the data's own (a LiDAR model there would be ignored, so it is refused)
REAL_SCAN_KINDS = ("kitti", "kitti-seq")
#: the options of ROS bags (the LiDAR keys give their mount where /tf_static does not)
BAG_KEYS = ("image", "scan", "depth", "camera_info", "tolerance")
#: the most frames a generated data set may have (train and val): about 15 GB on disk at 224x224
MAX_GENERATED = 100_000


@dataclass(frozen=True)
class DataSpec:
    kind: str          # synthetic | nyu | kitti | rosbag | synthetic-seq | kitti-seq | frames | rosbag-seq
    path: str = ""
    train: int = 2000
    val: int = 200
    options: tuple[tuple[str, str], ...] = ()   # sorted (key, value) pairs

    @property
    def is_sequence(self) -> bool:
        return self.kind in SEQUENCE_KINDS

    @property
    def option_dict(self) -> dict[str, str]:
        return dict(self.options)

    @property
    def lidar(self) -> LidarModel | None:
        """The LiDAR model the options give, or None (the paper's ideal centre-row scan)."""
        keys = {k: v for k, v in self.options if k not in BAG_KEYS and k != "val"}
        return lidar_model(keys, f"data '{self}'") if keys else None

    @property
    def val_option(self) -> str | None:
        return self.option_dict.get("val")

    def __str__(self) -> str:
        if self.kind in GENERATED_DEFAULTS:
            default = (self.train, self.val) == GENERATED_DEFAULTS[self.kind]
            base = self.kind if default else f"{self.kind}:{self.train}:{self.val}"
        else:
            base = f"{self.kind}:{self.path}"
        return base + "".join(f",{k}={v}" for k, v in self.options)


def _options(parts: list[str], kind: str, spec: str) -> tuple[tuple[str, str], ...]:
    known = set(LIDAR_KEYS) | set(RADIAN_KEYS) | {"T_cam_lidar", "val"} | (set(BAG_KEYS) if kind.startswith("rosbag") else set())
    out = {}
    for part in parts:
        key, eq, value = part.partition("=")
        key, value = key.strip(), value.strip()
        if not eq or not key or not value:
            raise UserError(f"data '{spec}': option '{part}' must be KEY=VALUE (e.g. tilt=2)")
        if key not in known:
            raise UserError(f"data '{spec}': unknown option '{key}'; {kind} takes {', '.join(sorted(known))}")
        if key in out:
            raise UserError(f"data '{spec}': option '{key}' is given twice")
        out[key] = value
    if kind in REAL_SCAN_KINDS and set(out) - {"val"}:
        raise UserError(f"data '{spec}': {kind} brings its own scan (the Velodyne's ring); a LiDAR model "
                        "applies to simulated scans and to bags or folders without a mount")
    return tuple(sorted(out.items()))


def parse_data_spec(spec: "str | DataSpec") -> DataSpec:
    """The :class:`DataSpec` of ``spec``, every part checked (a path that exists, options that mean
    something for its kind, a LiDAR model that is one), or a :class:`UserError`."""
    if isinstance(spec, DataSpec):
        return spec
    head, *opts = str(spec).split(",")
    kind, _, rest = head.partition(":")
    kind = kind.lower().strip()
    if kind not in GENERATED_DEFAULTS and kind not in PATH_KINDS:
        raise UserError(f"unknown data set '{spec}': {SPEC_HELP}")
    options = _options(opts, kind, str(spec))
    if kind in GENERATED_DEFAULTS:
        parts = [p for p in rest.split(":") if p] if rest else []
        try:
            nums = [int(p) for p in parts]
        except ValueError:
            raise UserError(f"data '{spec}': {kind} takes frame counts, e.g. {kind}:2000:200") from None
        train = nums[0] if nums else GENERATED_DEFAULTS[kind][0]
        val = nums[1] if len(nums) > 1 else max(train // 10, 4)
        if train < 1 or val < 1:
            raise UserError(f"data '{spec}': frame counts must be positive")
        if train + val > MAX_GENERATED:
            raise UserError(f"data '{spec}': at most {MAX_GENERATED:,} generated frames in all (each is kept on "
                            "disk); use real data for more")
        if "val" in dict(options):
            raise UserError(f"data '{spec}': {kind} generates its own validation frames; give their count "
                            f"({kind}:TRAIN:VAL), not val=")
        parsed = DataSpec(kind, "", train, val, options)
    else:
        if not rest:
            raise UserError(f"data '{spec}': give a path, e.g. {kind}:/data/{kind}")
        if not Path(rest).exists():
            raise UserError(f"data '{spec}': {rest} does not exist")
        parsed = DataSpec(kind, rest, options=options)
        _check_val(parsed, str(spec))
    parsed.lidar  # noqa: B018  (checks the LiDAR model now, at the edge)
    return parsed


def _check_val(ds: DataSpec, spec: str) -> None:
    val = ds.val_option
    if val is None:
        return
    if ds.kind == "nyu" and Path(ds.path).is_file() and not _is_number(val):
        if not Path(val).is_file():
            raise UserError(f"data '{spec}': the validation CSV {val} does not exist")
        if Path(val).resolve() == Path(ds.path).resolve():
            raise UserError(f"data '{spec}': val= names the training CSV itself; give another CSV or a share")
        return
    parse_share(val, f"data '{spec}'")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def with_lidar(spec: "str | DataSpec", model_options: dict) -> str:
    """``spec`` with a LiDAR model's keys (a ``lidar.yaml``'s, checked) as its options, canonical:
    what ``--lidar FILE`` makes of ``--data``. A ``T_cam_lidar`` matrix is written as the 12 numbers
    of its top three rows joined by ':'."""
    ds = parse_data_spec(spec)
    options = dict(model_options)
    if isinstance(options.get("mount"), dict):
        options.update(options.pop("mount"))
    lidar_model(options, "--lidar")
    given = sorted(k for k in ds.option_dict if k in LIDAR_KEYS or k in RADIAN_KEYS or k == "T_cam_lidar")
    if given:
        raise UserError(f"data '{spec}' gives the LiDAR key {given[0]!r} and --lidar gives a LiDAR too; use one")
    extra = []
    for key, value in options.items():
        if key == "T_cam_lidar":
            value = ":".join(f"{x:.9g}" for x in rigid_transform(value, "--lidar")[:3].ravel())
        else:
            value = f"{float(value):.9g}"
        extra.append(f"{key}={value}")
    return str(parse_data_spec(",".join([str(ds), *extra])))
