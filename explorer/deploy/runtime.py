"""The anytime runtime: runs exported stage graphs in order with onnxruntime and returns the best
depth map completed within a deadline (path 0, the interpolated scan, at worst). Another thread can
halt it at any moment (``AnytimeRunner.halt``) and get the best map so far."""

from __future__ import annotations

import io
import math
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from explorer.deploy._arena_choice import ArenaChoice
from explorer.deploy.manifest import MANIFEST, Manifest, Stage, read_manifest  # noqa: F401  (MANIFEST: its callers' name)
from explorer.deploy.sessions import check_provider
from explorer.errors import UserError
from explorer.files import read_image as read_image_file
from explorer.files import (check_writable_folder, read_text, refuse_overwriting_inputs, scratch_dir,
                            write_atomically)
from explorer.scan import (  # noqa: F401  (read_intrinsics: the runtime's face for robot code)
    LidarModel,
    check_camera_matrix,
    check_principal_point,
    column_scan,
    project_scan,
    read_intrinsics,
    read_lidar_yaml,
    read_ranges,
    rigid_transform,
)
from explorer.scan import scale_intrinsics as scale_box_intrinsics

#: ``AnytimeRunner(arenas=...)``
ARENAS = ("both", "shared", "own")


@dataclass
class AnytimeResult:
    depth: np.ndarray                 # (H, W) metres
    path: int                         # which path it is
    ready_ms: float                   # when that path was ready, from the start of the run
    completed: list[tuple[int, float]] = field(default_factory=list)  # (path, ready ms)
    halted: bool = False


@dataclass
class ProjectedScan:
    """A LiDAR's ranges in the model's input (:func:`project_ranges`): ``scan`` (W,) metres per column,
    0 = none (what :meth:`AnytimeRunner.run` takes); ``rows`` (W,) the input row of each column's
    return, interpolated between columns that have one; ``row`` their median; ``columns`` how many
    columns have a return."""
    scan: np.ndarray
    rows: np.ndarray
    row: int
    columns: int


class _Watchdog:
    """One thread per runner that halts its run at the deadline. A timer thread started for every run
    costs a share of every run; this thread is started once, and woken only when a run's deadline comes before the
    end of the wait it is in: runs with one deadline each, one after another, wake it about once per
    deadline instead of once per run (each wake takes the interpreter's lock from the thread that is
    about to start a stage)."""

    def __init__(self, halt: Callable[[], None]) -> None:
        self._halt = halt
        self._cond = threading.Condition()
        self._at: float | None = None     # perf_counter() time to halt at
        self._stopped = False
        self._thread: threading.Thread | None = None
        self._until = math.inf            # when the thread's current wait ends (inf: it waits to be woken)

    def arm(self, at: float) -> None:
        with self._cond:
            self._at = at
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="anytime-deadline", daemon=True)
                self._thread.start()
            if at < self._until:   # else it wakes before the deadline anyway and waits again till then
                self._cond.notify()

    def disarm(self) -> None:
        with self._cond:
            self._at = None      # not woken: it finds nothing to do at the old deadline

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()

    def _loop(self) -> None:
        with self._cond:
            while not self._stopped:
                if self._at is None:
                    self._until = math.inf
                    self._cond.wait()
                    continue
                left = self._at - time.perf_counter()
                if left > 0:
                    self._until = self._at
                    self._cond.wait(left)
                    continue
                self._at = None
                self._halt()


class AnytimeRunner:
    def __init__(self, model_dir: str | Path, threads: int | None = None, warmup: bool = True,
                 provider: str = "CPUExecutionProvider", handoff: bool = True,
                 arenas: str = "both") -> None:
        """``handoff``: stages hand tensors over as onnxruntime holds them where it applies
        (``explorer.probe.rewrites``): fp32 ones in its blocked layout (``NAME.nchwc``), ones that two int8 stages
        pass uint8 (``NAME.uint8``, ``NAME.uint8_nhwc``); ``handed_off`` says which and how.
        ``session_sets``: ``sessions`` (one memory arena shared by the process's sessions) and, where
        that arena is in use, the same graphs each with an arena of its own; a run uses the set that
        ``arena_choice`` picks (``explorer.deploy._arena_choice``). ``arenas``: "both" (that), "shared" or
        "own" (only that set: for timing one of them)."""
        import onnxruntime as ort

        from explorer.deploy.sessions import session
        from explorer.probe import shared_arena
        check_provider(provider)
        if arenas not in ARENAS:
            raise UserError(f"arenas={arenas!r}: use one of {', '.join(ARENAS)}")
        self.provider = provider
        self.dir = Path(model_dir)
        self.manifest = read_manifest(self.dir)
        self.input_size = tuple(self.manifest.input_size)
        self.scan_row = self.manifest.scan_row
        # graphs exported for a slanted scan line take each column's row (``scan_rows``) beside the scan
        self.rows_input = self.manifest.scan_rows_input
        self.path_errors = measured_errors(self.manifest)
        self.last_scan: ProjectedScan | None = None   # the last scan_from_ranges's projection
        self._row_warned = False
        self.sessions: list[tuple[Stage, object, list[str], list[str]]] = []
        self.handed_off: dict[str, str] = {}   # tensor passed between stages -> its form ("blocked", ...)
        self._graphs: list[tuple[bytes, bool]] = []   # each session's graph, and whether onnxruntime optimises it
        handoff = handoff and provider == "CPUExecutionProvider"   # its NCHWc kernels and QDQ fusions
        with scratch_dir("runtime") as tmp:
            optimized = Path(tmp)
            for k, st in enumerate(self.manifest.stages):
                f = self.dir / st.file
                try:
                    graph = f.read_bytes()
                    sess = session(graph, threads, provider,
                                   save_optimized=optimized / f"{k}.onnx" if handoff else None)
                except Exception as exc:  # onnxruntime raises its own types for corrupt graphs
                    raise UserError(f"{f}: not a loadable ONNX graph ({str(exc).splitlines()[0][:100]})") from None
                self.sessions.append(_named(st, sess))
                self._graphs.append((graph, True))
            _check_chain(self.sessions, self.manifest.paths, self.dir, self.rows_input)
            if handoff:
                self.handed_off = self._hand_off(optimized, threads)
        # the same graphs again, each session with a memory arena of its own (``explorer.deploy._arena_choice``)
        self.session_sets = [self.sessions]
        if shared_arena() and arenas != "shared":
            own = [_named(st, session(graph, threads, provider, optimize=optimize, own_arena=True))
                   for (st, *_), (graph, optimize) in zip(self.sessions, self._graphs)]
            self.session_sets = [own] if arenas == "own" else [self.sessions, own]
            self.sessions = self.session_sets[0]
        del self._graphs   # the sessions hold what they need
        self.arena_choice = ArenaChoice(len(self.session_sets), len(self.sessions))
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._options: "ort.RunOptions | None" = None
        halt = weakref.WeakMethod(self.halt)   # the watchdog's thread must not keep the runner alive
        self._watchdog = _Watchdog(lambda: (h := halt()) is not None and h())
        weakref.finalize(self, self._watchdog.stop)
        if warmup:
            h, w = self.input_size
            img, scan = self.check(np.zeros((3, h, w), np.float32), np.ones(w, np.float32))
            for sessions in self.session_sets:   # untimed: a first run is slower than the rest
                self._depths(sessions, img, scan)

    def _hand_off(self, optimized: Path, threads: int | None) -> dict[str, str]:
        """Replaces the sessions by ones made from their optimised graphs rewritten to hand tensors over
        as onnxruntime holds them, when a rewrite applies and gives the same depth maps; the names handed
        over and how."""
        import onnx

        from explorer.deploy.sessions import session
        from explorer.probe import hand_off_blocked, hand_off_quantized
        try:
            models = [onnx.load(str(optimized / f"{k}.onnx")) for k in range(len(self.sessions))]
            ins, outs = [s[2] for s in self.sessions], [s[3] for s in self.sessions]
            handed = dict.fromkeys(hand_off_blocked(models, ins, outs), "blocked")
            handed.update(hand_off_quantized(models, ins, outs))
            if not handed:
                return {}
            rewritten = [_named(st, session(m.SerializeToString(), threads, self.provider, optimize=False))
                         for (st, *_), m in zip(self.sessions, models)]
            h, w = self.input_size
            rng = np.random.default_rng(0)
            img = rng.random((1, 3, h, w), dtype=np.float32)
            scan = rng.uniform(0.5, 10.0, (1, w)).astype(np.float32)
            same = all(np.allclose(a, b, rtol=1e-5, atol=1e-6) for a, b in
                       zip(self._depths(self.sessions, img, scan), self._depths(rewritten, img, scan)))
        except Exception:   # an onnxruntime whose optimised graphs this rewrite does not know
            return {}
        if not same:
            return {}
        self.sessions = rewritten
        self._graphs = [(m.SerializeToString(), False) for m in models]
        return handed

    def _depths(self, sessions: list, img: np.ndarray, scan: np.ndarray, rows=None) -> list[np.ndarray]:
        env = {"image": img, "scan": scan, **self.row_feed(rows)}
        for _, sess, ins, outs_names in sessions:
            env.update(zip(outs_names, sess.run(outs_names, {n: env[n] for n in ins})))
        return [env[f"depth_{p}"][0, 0] for p in range(self.manifest.paths)]

    def depths(self, image: np.ndarray, scan: np.ndarray, rows=None) -> list[np.ndarray]:
        """Every path's depth map (no deadline), in order."""
        return self._depths(self.sessions, *self.check(image, scan), rows)

    def row_feed(self, rows=None) -> dict[str, np.ndarray]:
        """What the graphs take of the scan's rows: nothing, or where they take each column's
        (``scan_rows_input``), ``rows`` (one per image column; default the manifest's row for all)."""
        if not self.rows_input:
            return {}
        h, w = self.input_size
        r = np.full(w, self.scan_row, np.int64) if rows is None else np.asarray(rows).reshape(-1)
        if r.shape != (w,) or not np.isfinite(r).all() or (r < 0).any() or (r >= h).any():
            raise UserError(f"scan rows: one image row (0 to {h - 1}) per column ({w}) is needed, got "
                            f"{np.asarray(rows).size} value(s)")
        return {"scan_rows": r.astype(np.int64)[None]}

    def check(self, image: np.ndarray, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.input_size
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] == 3 and img.shape[0] != 3:
            img = img.transpose(2, 0, 1)
        if img.ndim != 3 or img.shape != (3, h, w):
            raise UserError(f"image has shape {tuple(np.asarray(image).shape)}, the model takes {h}x{w} RGB "
                            f"(resize it to {w}x{h} first)")
        if img.dtype == np.uint8:
            img = img.astype(np.float32) / 255.0
        s = np.asarray(scan, dtype=np.float32).reshape(-1)
        if s.shape != (w,):
            raise UserError(f"scan has {s.size} values, the model takes one per image column ({w})")
        if not np.isfinite(s).all() or (s < 0).any():
            raise UserError("scan must hold finite depths >= 0 (0 = no return)")
        return np.ascontiguousarray(img[None], dtype=np.float32), s[None]   # no copy when it is already so

    def scan_from_ranges(self, ranges, lidar: LidarModel, K: np.ndarray,
                         image_size: tuple[int, int]) -> np.ndarray:
        """The per-column scan (W,) at the model's input size that :meth:`run` takes, from a LiDAR's
        ``ranges`` (one per beam of ``lidar``, metres; inf, nan or 0 = no return) projected through
        ``K``, the camera matrix of the image at its own size ``image_size`` (H, W), scaled to the
        input size as the image is resized (:func:`fit_image`). The projection, with each column's row
        and their median, is kept in ``last_scan``. If that median lies more than one feature row
        (input height / 16) from the row the network was trained with its scan on, says so once
        (stderr)."""
        projected = project_ranges(ranges, lidar, K, image_size, self.input_size)
        self.last_scan = projected
        warning = None if self.rows_input else off_row_warning(projected.row, self.scan_row, self.input_size[0])
        if warning and not self._row_warned:
            self._row_warned = True
            print(warning, file=sys.stderr, flush=True)
        return projected.scan

    def improves(self, path: int, than: int) -> bool:
        """Whether ``path``'s measured error is lower than path ``than``'s (a later path is taken where
        the export measured nothing)."""
        if self.path_errors is None:
            return True
        return self.path_errors[path] < self.path_errors[than]

    def halt(self) -> None:
        """Stops the current run as soon as possible; it returns the best map completed so far."""
        self._halt.set()
        with self._lock:
            if self._options is not None:
                self._options.terminate = True

    def run(self, image: np.ndarray, scan: np.ndarray, deadline_ms: float | None = None,
            on_path: "Callable[[int, float], None] | None" = None, rows=None) -> AnytimeResult:
        """Runs the stages in order; returns the most accurate path ready within ``deadline_ms`` (None:
        all), by the errors the export measured (:meth:`improves`): never one less accurate than a
        path it already has.
        ``on_path(path, ready_ms)`` is called as each path becomes ready. ``rows``: each column's scan
        row, for graphs that take them (``row_feed``; :meth:`scan_from_ranges` gives them)."""
        import onnxruntime as ort
        img, s = self.check(image, scan)
        self._halt.clear()
        env = {"image": img, "scan": s, **self.row_feed(rows)}
        t0 = time.perf_counter()
        if deadline_ms is not None:
            self._watchdog.arm(t0 + max(deadline_ms, 0.0) / 1000.0)
        best: tuple[int, np.ndarray | None, float] | None = None
        completed = []
        halted = False
        opts = ort.RunOptions()
        path0 = None
        option = self.arena_choice.pick()
        try:
            for k, (st, sess, ins, out_names) in enumerate(self.session_sets[option]):
                if st.is_scan_path:
                    # the scan's own map is available at once (its cost is ~0) and is computed only
                    # if it is the answer: a run that reaches path 1 never needs it
                    path0 = (sess, ins, out_names)
                    best = (0, None, 0.0)
                    completed.append((0, 0.0))
                    if on_path is not None:
                        on_path(0, 0.0)
                    continue
                if best is not None and self._halt.is_set():
                    halted = True
                    break
                if best is not None and self._options is None:
                    # path 0 always completes (the floor of every answer); later stages can be cut
                    with self._lock:
                        self._options = opts
                    if self._halt.is_set():
                        halted = True
                        break
                started = time.perf_counter()
                try:
                    outs = sess.run(out_names, {n: env[n] for n in ins}, opts)
                except Exception:
                    if self._halt.is_set() and best is not None:
                        halted = True
                        break  # terminated mid-stage: keep what was ready
                    raise
                done = time.perf_counter()
                self.arena_choice.record(option, k, (done - started) * 1000.0)
                ready = (done - t0) * 1000.0
                env.update(zip(out_names, outs))
                path = st.path
                if path is not None:
                    if path == 0:
                        ready = 0.0  # the scan itself: available at once (its cost is ~0)
                    within = deadline_ms is None or ready <= deadline_ms or path == 0
                    if within:
                        if best is None or self.improves(path, best[0]):
                            best = (path, env[f"depth_{path}"], ready)
                        completed.append((path, ready))
                        if on_path is not None:
                            on_path(path, ready)
                    else:
                        halted = True
                        break
        finally:
            if deadline_ms is not None:
                self._watchdog.disarm()
            with self._lock:
                self._options = None
        path, depth, ready = best
        if depth is None:
            sess, ins, out_names = path0
            depth = sess.run(out_names, {n: env[n] for n in ins})[0]   # a RunOptions of its own: never cut
        return AnytimeResult(depth[0, 0], path, ready, completed, halted)


def _check_chain(sessions: list, paths: int, folder: Path, rows_input: bool = False) -> None:
    """Every graph reads only the image, the scan (and its rows, where the manifest says the graphs take
    them) and what graphs before it output, and every path's depth map is output by one of them: else
    the graphs are not the ones the manifest describes."""
    have = {"image", "scan", *(("scan_rows",) if rows_input else ())}
    for stage, _, ins, outs in sessions:
        missing = [n for n in ins if n not in have]
        if missing:
            raise UserError(f"{folder / stage.file}: reads {missing[0]}, which no graph before it outputs: "
                            "the graphs do not match the manifest (export the model again)")
        have.update(outs)
    lacking = [f"depth_{p}" for p in range(paths) if f"depth_{p}" not in have]
    if lacking:
        raise UserError(f"{folder}: no graph outputs {lacking[0]} of the manifest's {paths} paths: the graphs do "
                        "not match the manifest (export the model again)")


def _named(stage: Stage, sess) -> tuple[Stage, object, list[str], list[str]]:
    # names looked up once: get_inputs() builds new objects on every call
    return stage, sess, [i.name for i in sess.get_inputs()], [o.name for o in sess.get_outputs()]


def read_scan(path: Path) -> np.ndarray:
    """One depth in metres per image column (0 = no return), from ``.npy`` or text (CSV or spaces)."""
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give --scan one scan file (.npy, or text)")
    if not path.is_file():
        raise UserError(f"{path}: no such scan file")
    try:
        if path.suffix == ".npy":
            scan = np.load(path, allow_pickle=False).astype(np.float32).reshape(-1)
        else:
            scan = np.array([float(x) for x in read_text(path, "scan").replace(",", " ").split()], dtype=np.float32)
    except (ValueError, OSError, EOFError) as exc:
        raise UserError(f"{path}: unreadable scan ({type(exc).__name__}); give one depth in metres per image "
                        "column") from None
    if not np.isfinite(scan).all() or (scan < 0).any():
        raise UserError(f"{path}: scan depths must be finite and non-negative metres (0 = no return)")
    return scan


def read_image(path: Path) -> np.ndarray:
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give --image one image file")
    if not path.is_file():
        raise UserError(f"{path}: no such image")
    return read_image_file(path, "RGB")


#: what ``explorer run --out`` writes: 16-bit millimetres, or float32 metres
DEPTH_SUFFIXES = (".png", ".npy")


def check_depth_out(out: Path) -> Path:
    """``out`` if a depth map can be written there (a known suffix, a folder that exists or can be made),
    checked before the model runs."""
    if out.suffix.lower() not in DEPTH_SUFFIXES:
        raise UserError(f"{out}: write the depth map as .png (16-bit millimetres) or .npy (float32 metres)")
    if out.is_dir():
        raise UserError(f"{out}: is a folder; give a file name ending in .png or .npy")
    check_writable_folder(out.parent, "depth map", "give --out a path you can write")
    return out


def write_depth(depth: np.ndarray, out: Path) -> None:
    check_depth_out(out)
    buffer = io.BytesIO()
    if out.suffix.lower() == ".npy":
        np.save(buffer, depth.astype(np.float32))
    else:
        from PIL import Image
        Image.fromarray(np.clip(depth * 1000.0, 0, 65535).astype(np.uint16)).save(buffer, format="PNG")
    write_atomically(out, buffer.getvalue())


def run_files(model_dir: Path, image: Path, scan: Path, deadline_ms: float, out: Path | None,
              threads: int | None = None, provider: str = "CPUExecutionProvider",
              lidar: Path | None = None, intrinsics: Path | None = None) -> dict:
    """``explorer run``. With ``lidar`` (a ``lidar.yaml``) and ``intrinsics`` (K of ``image`` as it is),
    ``scan`` holds one range per beam, projected into the image (:meth:`AnytimeRunner.scan_from_ranges`),
    and the image may be any size (resized to the model's); without them, one depth per column."""
    check_provider(provider)   # every mistake is said before any file is read
    if lidar is not None and intrinsics is None:
        raise UserError("--lidar needs --intrinsics FILE: the camera matrix of --image (fx fy cx cy, or the "
                        "9 entries of K) to project the scan with")
    if intrinsics is not None and lidar is None:
        raise UserError("--intrinsics is read only with --lidar lidar.yaml (a scan of ranges by angle); "
                        "a per-column --scan needs neither")
    if out is not None:
        check_depth_out(out)
        refuse_overwriting_inputs(out, "--out", {"--image": image, "--scan": scan, "--lidar": lidar,
                                                 "--intrinsics": intrinsics})
    ranges = None
    if lidar is None:
        image_pixels, scan_depths = read_image(image), read_scan(scan)
    else:
        model, K = read_lidar_yaml(Path(lidar)), read_intrinsics(Path(intrinsics))
        if not scan.is_file():
            raise UserError(f"{scan}: no such scan file")
        ranges = read_ranges(scan, model.beams)
        image_pixels = read_image(image)
        check_principal_point(K, image_pixels.shape[:2], str(intrinsics))
    # one run: nothing to choose between sets by
    runner = AnytimeRunner(model_dir, threads, provider=provider, arenas="shared")
    extra = {}
    if ranges is not None:
        scan_depths = runner.scan_from_ranges(ranges, model, K, image_pixels.shape[:2])
        image_pixels = fit_image(image_pixels, runner.input_size)
        p = runner.last_scan
        have = p.rows[p.scan > 0]
        extra = {"scan_row": runner.scan_row, "scan_rows": [int(have.min()), int(have.max())],
                 "projected_row": p.row, "scan_columns": p.columns}
    result = runner.run(image_pixels, scan_depths, deadline_ms,
                        rows=runner.last_scan.rows if ranges is not None else None)
    if out is not None:
        write_depth(result.depth, out)
    return {"path": result.path, "ready_ms": result.ready_ms, "deadline_ms": deadline_ms,
            "completed_paths": len(result.completed), "timeline": result.completed,
            "out": str(out) if out else None, "provider": provider, **extra}


def scale_intrinsics(K: np.ndarray, image_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """K of an image of ``image_size`` (H, W) resized whole to ``size`` (:func:`explorer.scan.scale_intrinsics`)."""
    return scale_box_intrinsics(K, (0, 0, *image_size), size)


def fit_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W, 3) uint8 RGB resized to ``size`` (H, W), bilinear (Pillow), as
    :meth:`AnytimeRunner.scan_from_ranges` scales K; the image itself when it has that size."""
    from PIL import Image
    pixels = np.asarray(image)
    if pixels.shape[:2] == tuple(size):
        return pixels
    if pixels.ndim != 3 or pixels.shape[2] != 3 or pixels.dtype != np.uint8:
        raise UserError(f"image has shape {pixels.shape} ({pixels.dtype}): fit_image takes (H, W, 3) uint8 RGB")
    return np.asarray(Image.fromarray(pixels).resize((size[1], size[0]), Image.Resampling.BILINEAR))


def project_ranges(ranges, lidar: LidarModel, K: np.ndarray, image_size: tuple[int, int],
                   size: tuple[int, int]) -> ProjectedScan:
    """``ranges`` (one per beam of ``lidar``, metres; inf, nan, 0 or out of its range = no return)
    projected through ``K`` of an image of ``image_size`` (H, W), scaled to ``size`` (the model's
    input), nearest return per column."""
    try:
        r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise UserError("ranges must be numbers (metres; inf, nan or 0 = no return)") from None
    if r.size != lidar.beams:
        raise UserError(f"{r.size} ranges, the LiDAR's model has {lidar.beams} beams (angle_min .. angle_max by "
                        "angle_increment); give one range per beam")
    if len(image_size) != 2 or min(image_size) < 1:
        raise UserError(f"image_size {tuple(image_size)}: give the image's (height, width) in pixels")
    laser = lidar.scan(np.where(r > 0, r, np.inf))
    laser.check("LiDAR model")
    K_input = scale_intrinsics(check_camera_matrix(K, "intrinsics"), tuple(image_size), tuple(size))
    points = project_scan(laser, rigid_transform(lidar.transform, "LiDAR model"), K_input, tuple(size))
    if len(points.z) == 0:
        raise UserError("no return of this scan lands in the image: check the mount in lidar.yaml and the intrinsics")
    scan, rows, row = column_scan(points, tuple(size))
    return ProjectedScan(scan, rows, row, int((scan > 0).sum()))


def off_row_warning(row: int, scan_row: int, height: int) -> str | None:
    """What to say when a scan lands on ``row`` (median) more than one feature row (height / 16, at
    stride 16) from the model's ``scan_row``; None when it is near enough."""
    if abs(row - scan_row) <= height / 16:
        return None
    return (f"warning: this LiDAR's scan lands on row {row} of the {height}-row input (median of its returns), "
            f"but the network was trained with its scan on row {scan_row} (the graphs read the scan's features "
            "there): its depths will be off; retrain with this LiDAR's mount (--lidar)")


def measured_errors(manifest: Manifest) -> list[float] | None:
    """Each path's error as the export measured it on the exported graphs (RMSE, or the photometric
    error where the frames had no depth); None where it measured none."""
    metrics = manifest.path_metrics
    for key in ("rmse", "photometric"):
        values = [m.get(key) for m in metrics]
        if values and all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            return [float(v) for v in values]
    return None


def measured_anytime(runner: AnytimeRunner, frames: list[dict], deadlines_ms: np.ndarray,
                     metric: str = "rmse") -> dict:
    """Runs every frame (as :func:`path_metrics` takes them) under every deadline; returns the mean loss
    of what came back per deadline and the measured anytime loss for U(0, max deadline) (deadlines on a
    uniform grid)."""
    from explorer.metrics import depth_metrics
    per_deadline = []
    paths = []
    for d in deadlines_ms:
        losses, ps = [], []
        for f in frames:
            res = runner.run(np.asarray(f["image"]), np.asarray(f["scan"]), float(d), rows=_rows(f))
            losses.append(depth_metrics(res.depth, np.asarray(f["depth"][0]))[metric])
            ps.append(res.path)
        per_deadline.append(float(np.mean(losses)))
        paths.append(float(np.mean(ps)))
    return {"deadlines_ms": [float(d) for d in deadlines_ms], "loss": per_deadline, "mean_path": paths,
            "anytime_loss": float(np.mean(per_deadline))}


def path_metrics(runner: AnytimeRunner, frames: list[dict]) -> list[dict[str, float]]:
    """Per-path metrics (FastDepth's conventions) of an exported model on ``frames`` (data set items, or
    the NumPy frames an export carries for ``explorer curve``)."""
    from explorer.metrics import PHOTOMETRIC, MetricAverager, depth_metrics
    averagers = [MetricAverager() for _ in range(runner.manifest.paths)]
    for f in frames:
        for p, depth in enumerate(runner.depths(np.asarray(f["image"]), np.asarray(f["scan"]), _rows(f))):
            averagers[p].add(depth_metrics(depth, np.asarray(f["depth"][0])))
            if bool(f.get("pose_known", False)):   # a sequence's frame with the camera's motion
                averagers[p].add({PHOTOMETRIC: _photometric(depth, f)})
    return [{"path": p, **a.result()} for p, a in enumerate(averagers)]


def _photometric(depth: np.ndarray, frame: dict) -> float:
    """:func:`explorer.training.selfsup.photometric_score` of one exported path's map (export measures with
    torch at hand; the runtime itself never needs it)."""
    import torch
    from explorer.training.selfsup import photometric_score
    batch = {k: torch.as_tensor(frame[k])[None] for k in ("image", "sources", "K", "pose")}
    return float(photometric_score(torch.as_tensor(depth, dtype=torch.float32).reshape(1, 1, *depth.shape[-2:]),
                                   batch)[0])


def _rows(frame: dict) -> "np.ndarray | None":
    """A data set item's scan row per column, where it has them."""
    rows = frame.get("scan_rows")
    return None if rows is None else np.asarray(rows)
