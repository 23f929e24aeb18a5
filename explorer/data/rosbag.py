"""ROS bags as depth data: a robot's camera frames, each paired with its 2D LiDAR scan (and depth image).

A bag is a ROS 1 ``.bag``, a ROS 2 folder (sqlite3 or MCAP storage) or a bare ``.mcap`` / ``.db3``
file, all read by ``rosbags.highlevel.AnyReader``: no ROS installation. Its options come from a YAML
file beside it (``run.bag``, ``run.mcap`` or the folder ``run/`` -> ``run.yaml``), then from the
command line, which wins::

    image: /camera/color/image_raw       # sensor_msgs/Image (rgb8 bgr8 rgba8 bgra8 mono8) or CompressedImage
    scan: /scan                          # sensor_msgs/LaserScan
    camera_info: /camera/color/camera_info
    depth: /camera/depth/image_rect      # 16UC1 (mm) or 32FC1 (m); optional, ``none`` for no depth
    tolerance: 0.05                      # seconds between an image and its scan (and depth image)
    val: 0.1                             # the share of the recording (its end) that validates
    lidar: {height: 0.05, tilt: 2}       # the LiDAR's mount (LIDAR_KEYS or T_cam_lidar)

A topic not named is found by its type when one topic alone has it. The mount comes from the bag's
``/tf_static`` (the chain from the scan's frame to the camera's), unless ``lidar:`` gives one: a
mount given is the user's word and wins. The bag is decoded once into an HDF5 cache
(``cache_dir()/rosbag/NAME-HASH.h5``, keyed by the bag's files and the options): datasets ``rgb``
(N, H, W, 3) uint8, ``depth`` (N, H, W) float32 metres (0 unknown; only with a depth topic),
``stamp_ns`` (N,) int64 (the image's), ``scan_params`` (N, 4) (angle_min, angle_increment, range_min,
range_max), ``ranges`` (flat float32) cut by ``ranges_offset`` (N + 1,); attributes ``K``,
``T_cam_lidar``, ``counts`` and ``topics`` (JSON). :class:`BagFrames` (supervised) and
:class:`BagSequence` (self-supervised) read it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from explorer.data._ros_messages import (
    COMPRESSED,
    DEPTH_TYPES,
    IMAGE,
    INFO,
    SCAN,
    TF,
    _decode_depth,
    _decode_image,
    _first_line,
    _frame,
    _image_size,
    _intrinsics,
    _nearest,
    _scan,
    _stamp,
    _tf_chain,
    _transform,
)
from explorer.data.odometry import camera_motion
from explorer.data.readers import RawFrame
from explorer.data.spec import BAG_KEYS as SPEC_BAG_KEYS
from explorer.scan import (LIDAR_KEYS, RADIAN_KEYS, LaserScan, check_principal_point, lidar_model, project_scan,
                           rigid_transform)
from explorer.scan import MOUNT_KEYS as LIDAR_MOUNT_KEYS
from explorer.data.sequences import SequenceSample
from explorer.data.splits import VAL_SHARE, parse_share, split_range
from explorer.data.synthetic import cache_dir, writing_cache
from explorer.errors import UserError
from explorer.files import read_yaml

try:   # imported here so that tests can stand in for it
    from rosbags.highlevel import AnyReader, AnyReaderError
except ImportError:   # pragma: no cover
    AnyReader = AnyReaderError = None

TOPIC_KEYS = ("image", "scan", "depth", "camera_info")
BAG_KEYS = (*SPEC_BAG_KEYS, "val")
MOUNT_KEYS = (*LIDAR_MOUNT_KEYS, "T_cam_lidar")
CACHE_VERSION = 1


@dataclass(frozen=True)
class BagOptions:
    """What to read from a bag: topics (None = found by type), the pairing tolerance (s), the
    validation share and the mount (16 numbers of T_cam_lidar, row-major) if one is given."""

    image: str | None = None
    scan: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    tolerance: float = 0.05
    val: float = VAL_SHARE
    mount: tuple[float, ...] | None = None
    source: str = field(default="", compare=False)   # where the options came from, for messages

    @property
    def key(self) -> str:
        """What the decoded frames depend on (the cache's key; ``val`` only splits them)."""
        return repr((self.image, self.scan, self.depth, self.camera_info, self.tolerance, self.mount))


def options_path(path: Path) -> Path:
    """The YAML beside a bag: its suffix replaced (a folder: its name plus ``.yaml``)."""
    path = Path(path)
    return path.parent / f"{path.name}.yaml" if path.is_dir() else path.with_suffix(".yaml")


def bag_options(path: Path, options: dict[str, str]) -> BagOptions:
    """The :class:`BagOptions` of the YAML beside ``path`` (if any; LiDAR keys under ``lidar:``)
    overridden by ``options`` (LiDAR keys among them), each checked; unknown keys name the known ones."""
    if Path(path).suffix.lower() in (".yaml", ".yml"):   # a ROS 2 bag's metadata.yaml, given for its folder
        raise UserError(f"{path}: a YAML file, not a bag: give the ROS 2 bag's folder (the one holding "
                        "metadata.yaml), or a .bag, .mcap or .db3 file")
    yml = options_path(path)
    if yml.is_dir():
        raise UserError(f"{yml}: is a folder where the bag's options file goes; move it away")
    data = read_yaml(yml, "bag options") if yml.is_file() else {}
    merged = data or {}
    if not isinstance(merged, dict) or not isinstance(merged.get("lidar") or {}, dict):
        raise UserError(f"{yml}: expected a mapping of {', '.join(BAG_KEYS)} and lidar: (a mapping of LiDAR keys)")
    lidar = dict(merged.pop("lidar", None) or {})
    for key in merged:
        if key not in BAG_KEYS:
            hint = " (LiDAR keys go under lidar:)" if key in LIDAR_KEYS or key in MOUNT_KEYS else ""
            raise UserError(f"{yml}: unknown key {key!r}{hint}; use {', '.join(BAG_KEYS)} or lidar")
    lidar.update(lidar.pop("mount", None) or {})
    given = {k: v for k, v in options.items() if k not in BAG_KEYS}
    for key in given:
        if key not in LIDAR_KEYS and key not in MOUNT_KEYS and key not in RADIAN_KEYS:
            raise UserError(f"{path}: unknown bag option {key!r}; use {', '.join(BAG_KEYS)} or the LiDAR keys "
                            f"{', '.join(LIDAR_KEYS)}, T_cam_lidar")
    if any(k in MOUNT_KEYS for k in given):   # a mount given anew replaces the file's
        lidar = {k: v for k, v in lidar.items() if k not in MOUNT_KEYS}
    merged.update({k: v for k, v in options.items() if k in BAG_KEYS})
    return _checked(merged, {**lidar, **given}, str(yml) if yml.is_file() else str(path))


def _checked(merged: dict, lidar: dict, where: str) -> BagOptions:
    topics = {k: merged.get(k) for k in TOPIC_KEYS}
    for key, value in topics.items():
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise UserError(f"{where}: {key} must be a topic name, got {value!r}")
    try:
        tolerance = float(merged.get("tolerance", 0.05))
    except (TypeError, ValueError):
        tolerance = math.nan
    if not math.isfinite(tolerance) or tolerance <= 0:
        raise UserError(f"{where}: tolerance must be a positive number of seconds, got {merged['tolerance']!r}")
    val = parse_share(str(merged["val"]), where) if "val" in merged else VAL_SHARE
    mount = None
    if lidar:
        model = lidar_model(lidar, where)
        mount = tuple(float(x) for x in model.transform.ravel()) if set(lidar) & set(MOUNT_KEYS) else None
    return BagOptions(**{k: v and v.strip() for k, v in topics.items()}, tolerance=tolerance, val=val,
                      mount=mount, source=where)


# -- reading the bag ------------------------------------------------------------------------------
def _check_path(path: Path) -> None:
    if not path.exists():
        raise UserError(f"{path}: no such bag (a ROS 1 .bag, a ROS 2 folder, or a .mcap / .db3 file)")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise UserError(f"{path}: not a ROS 2 bag (the folder has no metadata.yaml)")
    if path.is_file() and path.suffix not in (".bag", ".mcap", ".db3"):
        raise UserError(f"{path}: not a ROS bag (expected a .bag, .mcap or .db3 file, or a ROS 2 folder)")


def _open_reader(path: Path):
    """An opened AnyReader, or a UserError for a path that is not a readable bag."""
    from rosbags.typesys import Stores, get_typestore
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError, AssertionError) as exc:
        raise UserError(f"{path}: not a readable ROS bag ({_first_line(exc)})") from None
    return reader


def _choose(topics: dict[str, str], key: str, named: str | None, types: tuple[str, ...], where: str,
            exclude: tuple[str, ...] = (), needed: bool = True) -> str | None:
    """The topic for ``key``: the one named (which the bag must have, of one of ``types``), else the
    one topic of those types; several, or none where one is needed: a UserError naming them."""
    of_type = sorted(t for t, typ in topics.items() if typ in types)
    kind = " or ".join(t.replace("/msg/", "/") for t in types)
    if named is not None:
        for name in (named, "/" + named.lstrip("/")):
            if name in of_type:
                return name
        have = ", ".join(of_type) or "none"
        raise UserError(f"{where}: the bag has no {kind} topic {named!r} (its {kind} topics: {have}); "
                        f"set {key}=TOPIC")
    if key == "depth":
        candidates = [t for t in of_type if "depth" in t.lower() and topics[t] == IMAGE]
    else:
        candidates = [t for t in of_type if t not in exclude and "depth" not in t.lower()]
    if len(candidates) == 1:
        return candidates[0]
    if len(candidates) > 1:
        raise UserError(f"{where}: {len(candidates)} {kind} topics ({', '.join(candidates)}); "
                        f"name one, e.g. {key}={candidates[0]}")
    taken = [t for t in of_type if t in exclude]
    if needed and taken:   # the camera's own topic was named as the depth
        raise UserError(f"{where}: {taken[0]} is named as the depth, and no other topic is the camera's image; "
                        "name the depth topic with depth=TOPIC, or give depth=none")
    if needed:
        raise UserError(f"{where}: the bag has no {kind} topic (its topics: {', '.join(sorted(topics)) or 'none'})")
    return None


def choose_topics(topics: dict[str, str], opts: BagOptions, where: str) -> dict[str, str | None]:
    """The image, scan, depth (None if there is none) and camera_info topics of a bag."""
    no_depth = opts.depth is not None and opts.depth.lower() == "none"
    depth = None if no_depth else _choose(topics, "depth", opts.depth, (IMAGE,), where, needed=False)
    image = _choose(topics, "image", opts.image, (IMAGE, COMPRESSED), where, exclude=(depth,))
    if image == depth:
        raise UserError(f"{where}: image and depth name one topic ({image}); set image= and depth= apart")
    return {"image": image, "depth": depth, "scan": _choose(topics, "scan", opts.scan, (SCAN,), where),
            "camera_info": _choose(topics, "camera_info", opts.camera_info, (INFO,), where)}


@dataclass
class _Survey:
    """What the first pass over a bag learns: stamps of images and depth images (by their order in
    the bag), the scans, the camera info and the static transforms."""

    images: list[tuple[int, int]] = field(default_factory=list)   # (stamp ns, bag time ns)
    depths: list[tuple[int, int]] = field(default_factory=list)
    scans: list[tuple[int, LaserScan]] = field(default_factory=list)
    info: object = None
    image_frame: str = ""
    scan_frame: str = ""
    image_size: tuple[int, int] | None = None   # (H, W)
    edges: dict = field(default_factory=dict)   # frame -> [(other frame, T_other_frame)]


def _survey(reader, topics: dict, where: str) -> _Survey:
    """The first pass: every message of the chosen topics and /tf_static deserialized, pixels not
    decoded (the second pass decodes only the frames that pair)."""
    s = _Survey()
    tf_topics = [t for t, c in reader.topics.items() if t.lstrip("/") == "tf_static" and c.msgtype == TF]
    wanted = {v: k for k, v in topics.items() if v} | {t: "tf" for t in tf_topics}
    conns = [c for c in reader.connections if c.topic in wanted]
    for conn, t_bag, raw in reader.messages(connections=conns):
        kind, msg = wanted[conn.topic], reader.deserialize(raw, conn.msgtype)
        if kind == "tf":
            for ts in msg.transforms:
                parent, child, m = _frame(ts), str(ts.child_frame_id).strip().lstrip("/"), _transform(ts.transform)
                s.edges.setdefault(child, []).append((parent, m))
                s.edges.setdefault(parent, []).append((child, np.linalg.inv(m)))
        elif kind == "camera_info":
            s.info = s.info or msg
        elif kind == "scan":
            s.scans.append((_stamp(msg, t_bag), _scan(msg, _stamp(msg, t_bag), f"{where}: {conn.topic}")))
            s.scan_frame = s.scan_frame or _frame(msg)
        elif kind == "image":
            s.images.append((_stamp(msg, t_bag), int(t_bag)))
            s.image_frame = s.image_frame or _frame(msg)
            if s.image_size is None:
                s.image_size = _image_size(msg, conn.msgtype, f"{where}: {conn.topic}")
        else:
            if conn.msgtype != IMAGE or msg.encoding.lower() not in DEPTH_TYPES:
                enc = getattr(msg, "encoding", "compressed")
                raise UserError(f"{where}: {conn.topic}: depth encoding {enc!r}; expected 16UC1 (mm) or 32FC1 (m)")
            s.depths.append((_stamp(msg, t_bag), int(t_bag)))
    return s


@dataclass
class _Plan:
    """The frames to decode in time order: the (bag time, stamp) of each image and depth image, the scans."""

    image: list
    stamp: np.ndarray
    scans: list[LaserScan]
    depth: list | None
    counts: dict
    K: np.ndarray
    T: np.ndarray
    shape: tuple[int, int]


def _plan(s: _Survey, topics: dict, opts: BagOptions, where: str) -> _Plan:
    """Pairs each image with the nearest scan (and depth image) within the tolerance, and finds K and
    T_cam_lidar; every failure a user can fix is raised here, before a pixel is decoded."""
    for key, items in (("image", s.images), ("scan", s.scans)):
        if not items:
            raise UserError(f"{where}: the {key} topic {topics[key]} has no messages")
    if s.info is None:
        raise UserError(f"{where}: the camera_info topic {topics['camera_info']} has no messages (K is needed)")
    if topics["depth"] and not s.depths:
        raise UserError(f"{where}: the depth topic {topics['depth']} has no messages; set depth=none to skip it")
    K = _intrinsics(s.info, f"{where}: {topics['camera_info']}")
    T = _mount(s, opts, where)
    imgs = sorted(dict(s.images[::-1]).items())   # by stamp; of images stamped alike the first
    stamp = np.array([t for t, _ in imgs], np.int64)
    tol = int(round(opts.tolerance * 1e9))
    scans = sorted(range(len(s.scans)), key=lambda i: s.scans[i][0])
    scan_t = np.array([s.scans[i][0] for i in scans], np.int64)
    pick, off = _nearest(scan_t, stamp)
    ok = off <= tol
    counts = {"images": len(s.images), "duplicate": len(s.images) - len(imgs), "no_scan": int((~ok).sum())}
    depth = None
    if topics["depth"]:
        dep = sorted(s.depths)
        dpick, doff = _nearest(np.array([t for t, _ in dep], np.int64), stamp)
        dok = doff <= tol
        counts["no_depth"] = int((ok & ~dok).sum())
        if not (ok & dok).any() and ok.any():
            raise UserError(f"{where}: no image has a depth image within tolerance={opts.tolerance:g} s (the nearest "
                            f"is {doff.min() / 1e9:.3g} s away); raise tolerance= or set depth=none")
        ok &= dok
        depth = [(dep[k][1], dep[k][0]) for k in dpick[ok]]
    else:
        counts["no_depth"] = 0
    if not ok.any():
        raise UserError(f"{where}: no image has a scan within tolerance={opts.tolerance:g} s (the nearest pair is "
                        f"{off.min() / 1e9:.3g} s apart); raise tolerance= or check the stamps")
    counts["paired"] = int(ok.sum())
    shape = _shape(s, where)
    check_principal_point(K, shape, f"{where}: {topics['camera_info']}")
    paired = [s.scans[i][1] for i in np.array(scans, np.int64)[pick[ok]]]
    if not any(len(project_scan(scan, T, K, shape).z) for scan in paired):
        raise UserError(f"{where}: no scan lands in the image on any frame (T_cam_lidar puts every return outside "
                        "it or behind the camera); check the mount (/tf_static or lidar:)")
    image = [(imgs[k][1], imgs[k][0]) for k in np.nonzero(ok)[0]]
    return _Plan(image, stamp[ok], paired, depth, counts, K, T, shape)


def _mount(s: _Survey, opts: BagOptions, where: str) -> np.ndarray:
    """T_cam_lidar: the mount given, else the /tf_static chain from the scan's frame to the camera's."""
    if opts.mount is not None:
        return rigid_transform(np.reshape(opts.mount, (4, 4)), opts.source or where)
    camera = s.image_frame or _frame(s.info)
    T = _tf_chain(s.edges, s.scan_frame, camera) if s.scan_frame and camera else None
    if T is None:
        yml = options_path(Path(where)).name
        raise UserError(f"{where}: no /tf_static transform from the LiDAR's frame {s.scan_frame!r} to the camera's "
                        f"{camera!r}; add /tf_static to the bag or give the mount as lidar: (height, tilt, ... or "
                        f"T_cam_lidar) in {yml}, or T_cam_lidar= / height= ... as options")
    return rigid_transform(T, f"{where}: /tf_static {s.scan_frame} -> {camera}")


def _shape(s: _Survey, where: str) -> tuple[int, int]:
    """The image size, checked against the CameraInfo's (0 there: not given)."""
    h, w = s.image_size
    ih, iw = int(s.info.height), int(s.info.width)
    if ih and iw and (ih, iw) != (h, w):
        raise UserError(f"{where}: the images are {w}x{h}, the CameraInfo says {iw}x{ih}; name the camera_info= "
                        "topic of the image's camera")
    return h, w


# -- the cache ------------------------------------------------------------------------------------
def _fingerprint(path: Path) -> list:
    """What changes when the bag does: the files' names, sizes and modification times."""
    path = path.resolve()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return [str(path)] + [(str(p.relative_to(path.parent)), p.stat().st_size, p.stat().st_mtime_ns) for p in files]


def cache_path(path: Path, opts: BagOptions) -> Path:
    text = json.dumps([CACHE_VERSION, _fingerprint(path), opts.key])
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(path).resolve().name)[:40]
    return cache_dir() / "rosbag" / f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:16]}.h5"


def _decode_into(reader, topics: dict, plan: _Plan, out, where: str) -> None:
    """The second pass: decodes the planned images and depth images into the cache ``out``
    (``explorer.files.Hdf5Writer``) at their frames (a message is known by its bag time and stamp,
    whatever order the bag yields it in)."""
    n, (h, w), h5 = len(plan.image), plan.shape, out.file
    datasets = {"image": h5.create_dataset("rgb", (n, h, w, 3), np.uint8, chunks=(1, h, w, 3), compression="lzf")}
    slots: dict = {}
    for i, key in enumerate(plan.image):
        slots.setdefault(("image", key), []).append(i)
    if plan.depth is not None:
        datasets["depth"] = h5.create_dataset("depth", (n, h, w), np.float32, chunks=(1, h, w), compression="lzf")
        for i, key in enumerate(plan.depth):
            slots.setdefault(("depth", key), []).append(i)
    kinds = {topics[k]: k for k in ("image", "depth") if topics[k]}
    for conn, t_bag, raw in reader.messages(connections=[c for c in reader.connections if c.topic in kinds]):
        kind, msg = kinds[conn.topic], reader.deserialize(raw, conn.msgtype)
        frames = slots.get((kind, (int(t_bag), _stamp(msg, t_bag))))
        if frames:
            at = f"{where}: {conn.topic}"
            arr = _decode_image(msg, conn.msgtype, at) if kind == "image" else _decode_depth(msg, at)
            if arr.shape[:2] != (h, w):
                raise UserError(f"{at}: an image is {arr.shape[1]}x{arr.shape[0]}, the camera's are {w}x{h}")
            for i in frames:
                datasets[kind][i] = arr
            out.check()   # a disk that filled: stop here, not after decoding the rest


@contextmanager
def _folders_made_undone(folder: Path) -> Iterator[None]:
    """Removes again, when the block raises, the folders up to ``folder`` that it made (those missing
    now, deepest first, each only while empty: another process's files in one keep it)."""
    missing = []
    for f in (folder, *folder.parents):
        if f.exists():
            break
        missing.append(f)
    try:
        yield
    except BaseException:
        for f in missing:
            try:
                f.rmdir()
            except OSError:
                break
        raise


#: what a reader of the cache accepts, asked before the cache is written: ``accept(has_depth, n)``
#: (``n`` None: the frames not counted yet) raises the UserError of a bag it refuses.
Accept = Callable[[bool, int | None], object]


def build_cache(path: Path, opts: BagOptions, accept: Accept | None = None) -> Path:
    """Decodes the bag into its cache (if not there yet) and returns the cache's path. ``accept``
    refuses a bag before anything is written: once its topics are chosen (has it a depth topic) and
    once its frames are paired (how many). A UserError leaves the cache as it was: the file is
    written on a scratch name and renamed into place whole, and a folder made for it is removed."""
    _check_path(path)
    target = cache_path(path, opts)
    if target.is_file():
        return target
    where = str(path)
    reader = _open_reader(path)
    try:
        topic_types = {t: info.msgtype for t, info in reader.topics.items() if info.msgtype}
        topics = choose_topics(topic_types, opts, where)
        if accept is not None:
            accept(topics["depth"] is not None, None)
        plan = _plan(_survey(reader, topics, where), topics, opts, where)
        n, (h, w) = len(plan.image), plan.shape
        if accept is not None:
            accept(plan.depth is not None, n)
        need = n * h * w * (3 + (4 if plan.depth is not None else 0)) // 2   # LZF rarely halves them
        with _folders_made_undone(target.parent), writing_cache(target, need, "recording's cache") as out:
            _decode_into(reader, topics, plan, out, where)
            _write_meta(out.file, plan, topics)
    except AnyReaderError as exc:
        raise UserError(f"{path}: a message does not decode ({_first_line(exc)})") from None
    finally:
        reader.close()
    return target


def _write_meta(h5, plan: _Plan, topics: dict) -> None:
    h5.create_dataset("stamp_ns", data=plan.stamp)
    h5.create_dataset("scan_params", data=np.array(
        [[sc.angle_min, sc.angle_increment, sc.range_min, sc.range_max] for sc in plan.scans], np.float64))
    h5.create_dataset("ranges", data=np.concatenate([sc.ranges for sc in plan.scans]).astype(np.float32))
    h5.create_dataset("ranges_offset", data=np.cumsum([0] + [len(sc.ranges) for sc in plan.scans]).astype(np.int64))
    h5.attrs["K"], h5.attrs["T_cam_lidar"] = plan.K, plan.T
    h5.attrs["counts"], h5.attrs["topics"] = json.dumps(plan.counts), json.dumps(topics)
    h5.attrs["version"] = CACHE_VERSION


def frame_name(stamp_ns: int) -> str:
    """A frame's name: its image's stamp, ``t1700000000.123456789``."""
    return f"t{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}"


class _BagSource:
    """The cache of one bag (decoded on first use); its pixels are read per item, through a file
    opened once per process (a DataLoader's workers each open their own)."""

    def __init__(self, path: Path, options: dict, split: str) -> None:
        import h5py
        self.path, self.split = path, split
        self.options = bag_options(Path(path), dict(options))
        self.cache = build_cache(Path(path), self.options, accept=self._items)
        try:
            with h5py.File(self.cache, "r") as h5:
                self.K, self.T_cam_lidar = np.asarray(h5.attrs["K"]), np.asarray(h5.attrs["T_cam_lidar"])
                self.counts, self.topics = json.loads(h5.attrs["counts"]), json.loads(h5.attrs["topics"])
                self.stamps, self.params = np.asarray(h5["stamp_ns"]), np.asarray(h5["scan_params"])
                self.offsets, self.ranges = np.asarray(h5["ranges_offset"]), np.asarray(h5["ranges"])
                self.has_depth = "depth" in h5
        except (OSError, KeyError) as exc:   # damaged outside the package: decoded anew next time
            self.cache.unlink(missing_ok=True)
            raise UserError(f"{self.cache}: a damaged bag cache, removed ({_first_line(exc)}); run again") from None
        self.names = [frame_name(int(t)) for t in self.stamps]
        self._h5, self._pid = None, None
        self.items = self._items(self.has_depth, len(self.stamps))

    def _items(self, has_depth: bool, n: int | None) -> range | None:
        """The split's items of ``n`` paired frames (None while ``n`` is not known), or the UserError
        of a bag this reader refuses: asked before the cache is written, and again when it is read."""
        raise NotImplementedError

    def __getstate__(self) -> dict:   # pickled to a worker: without the open file
        return {**self.__dict__, "_h5": None, "_pid": None}

    def _read(self, name: str, i: int) -> np.ndarray:
        import h5py
        if self._h5 is None or self._pid != os.getpid():
            self._h5, self._pid = h5py.File(self.cache, "r"), os.getpid()
        return np.asarray(self._h5[name][i])

    def _depth(self, i: int, shape: tuple[int, int]) -> np.ndarray:
        return self._read("depth", i) if self.has_depth else np.zeros(shape, np.float32)

    def _scan(self, i: int) -> LaserScan:
        amin, inc, rmin, rmax = (float(x) for x in self.params[i])
        return LaserScan(amin, inc, rmin, rmax, self.ranges[self.offsets[i]:self.offsets[i + 1]], self.stamps[i] / 1e9)

    def _scan_points(self, i: int, shape: tuple[int, int]):
        return project_scan(self._scan(i), self.T_cam_lidar, self.K, shape)

    def __len__(self) -> int:
        return len(self.items)


class BagFrames(_BagSource):
    """Supervised frames of a bag with a depth topic: RGB, depth, and the scan projected into the
    image. Split in time (the end validates), 1% of the frames left out between, so that no
    neighbour of a validation frame trains."""

    def _items(self, has_depth: bool, n: int | None) -> range | None:
        path = self.path
        if not has_depth:
            raise UserError(f"{path}: no depth topic: train self-supervised with rosbag-seq:{path}, "
                            "or name depth=TOPIC")
        if n is None:
            return None
        return split_range(n, self.split, str(path), share=self.options.val, gap=max(1, round(0.01 * n)))

    def __getitem__(self, i: int) -> RawFrame:
        j = self.items[i]
        rgb = self._read("rgb", j)
        return RawFrame(rgb, self._depth(j, rgb.shape[:2]), None, self.names[j], self._scan_points(j, rgb.shape[:2]))

    def frame_names(self) -> list[str]:
        return [self.names[j] for j in self.items]


class BagSequence(_BagSource):
    """Self-supervised samples of a bag: each paired frame but the first and last, with its
    neighbours in time. Two targets left out between the splits, so that no frame of a validation
    sample is in a training one. ``max_depth``: the LiDAR's range_max.

    Validation samples carry the camera's motion to each neighbour as the LiDAR measures it
    (:mod:`explorer.data.odometry`): what scores each path where the bag has no depth."""

    kind = "frames"

    def __init__(self, path: Path, options: dict, split: str) -> None:
        super().__init__(path, options, split)
        self.max_depth = float(self.params[:, 3].max())
        self.poses = [self._poses(j) for j in self.items] if split == "val" else None

    def _items(self, has_depth: bool, n: int | None) -> range | None:
        if n is None:
            return None
        if n < 3:
            raise UserError(f"{self.path}: {n} paired frame(s); a sequence needs at least 3")
        return split_range(n - 2, self.split, str(self.path), share=self.options.val, gap=2, start=1)

    def _poses(self, j: int) -> list[np.ndarray] | None:
        """Camera-to-world of frames j-1, j, j+1, frame j's camera being the world; None where the scans
        do not pin either motion down."""
        motions = [camera_motion(self._scan(k), self._scan(j), self.T_cam_lidar) for k in (j - 1, j + 1)]
        if any(m is None for m in motions):
            return None
        return [motions[0], np.eye(4), motions[1]]

    def __getitem__(self, i: int) -> SequenceSample:
        j = self.items[i]
        frames = [self._read("rgb", k) for k in (j - 1, j, j + 1)]
        shape = frames[1].shape[:2]
        poses = self.poses[i] if self.poses is not None else None
        return SequenceSample(frames, self._depth(j, shape), self.K.copy(), poses, None, self.names[j],
                              self._scan_points(j, shape))

    def frame_names(self) -> list[str]:
        return sorted({self.names[k] for j in self.items for k in (j - 1, j, j + 1)})
