"""The probe's run over a bundle (resumable: results are written after every graph) and its
command line."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None


from .formats import (DEFAULT_PROVIDER, RESULTS_FORMAT, VERSION, WARMUP, BundleManifest, ProbeError, load_manifest,
                      read_results, write_atomically)
from .identity import device_identity
from .power import find_sensor, idle_power, inference_energy
from .scratch import sigterm_unwinds
from .sessions import _shared_pool, check_provider, default_threads, session, shared_pool_threads, thread_pool
from .timing import (REMEASURE_PASSES, SPEED_CHECK_EVERY, SPEED_DRIFT_WARN, _random_feeds, chain_runs,
                     chain_sessions, fixed_graph_timer, set_aside, slow_windows, slowness, speed_drift, speed_layer,
                     speed_stage, time_call, time_chain, wait_until_calm)


#: What the probe's ``progress(done, total, what)`` counts, each from 0 to its own total: the graphs
#: not timed yet, each pass of graphs timed again, the candidates whose energy is measured.
TIMING_GRAPHS, TIMING_AGAIN, MEASURING_ENERGY = "timing graphs", "timing again", "measuring energy"


def candidate_inputs(manifest: BundleManifest, rng: np.random.Generator,
                     cand: dict | None = None) -> dict[str, np.ndarray]:
    h, w = (cand or {}).get("input_size") or manifest.input_size
    return {"image": rng.random((1, 3, h, w), dtype=np.float32),
            "scan": rng.random((1, w), dtype=np.float32) * 5 + 0.5}


def schedule(layers: list[dict], cands: list[dict]) -> list[tuple[str, dict]]:
    """Layer graphs with the candidates spread evenly among them: a board that heats up and
    throttles (or a machine whose load drifts) then slows both kinds alike, and the fit, which
    reads them together, does not mistake the drift for a difference between them."""
    order: list[tuple[str, dict]] = [("layer", layer) for layer in layers]
    for j, cand in reversed(list(enumerate(cands))):
        order.insert(round((j + 0.5) * len(layers) / len(cands)), ("candidate", cand))
    return order


def run_probe(bundle_dir: "str | Path", out: "str | Path", provider: str = DEFAULT_PROVIDER,
              threads: int | None = None, repeats: int | None = None, energy: bool = True,
              root: str = "/", vcgencmd: str = "vcgencmd", idle_s: float = 2.0, window_s: float = 1.0,
              progress: Callable[[int, int, str], None] | None = None,
              log: Callable[[str], None] = lambda s: None, remeasure_passes: int = REMEASURE_PASSES,
              calm_wait_s: float | None = None, again: bool = False) -> dict:
    """Times every graph of the bundle (single layers, then each candidate's stages in order, each
    fed by the one before), then, where a power sensor is readable, the energy of whole inferences.
    Returns the results, also written (atomically, after every graph) to ``out``. Graphs timed while a
    speed check showed the machine slow are timed again in up to ``remeasure_passes`` more passes, each
    after waiting up to ``calm_wait_s`` (None: ``CALM_WAIT_S``) for the machine's usual speed. ``progress(done, total, what)``:
    each pass (``TIMING_GRAPHS``, then ``TIMING_AGAIN``) and the energy (``MEASURING_ENERGY``) counted
    from 0, called with 0 when it starts."""
    bundle_dir, out = Path(bundle_dir), Path(out)
    manifest = load_manifest(bundle_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    check_provider(provider)
    threads = threads or default_threads()
    _shared_pool(threads)
    threads = shared_pool_threads() or threads
    repeats = repeats or int(manifest.repeats)
    cond = {"provider": provider, "threads": threads, "thread_pool": thread_pool(),
            "repeats": repeats, "warmup": WARMUP, "statistic": "median", "stage_graphs": "timed in sequence"}
    # again: the caller's own results timed once more in part (explorer calibrate's slow graphs), where
    # resuming them and the speed's note were said by the first run
    res = _open_results(out, manifest, cond, provider, threads, root, (lambda s: None) if again else log)
    timing = _Timing(res, manifest, bundle_dir, out, threads, provider, repeats, progress)
    timing.all_passes(remeasure_passes, calm_wait_s, log)
    write_atomically(out, res)
    if not again:
        _warn_of_drift(res, log)
    if energy:
        _probe_energy(res, manifest, bundle_dir, out, provider, threads, root, vcgencmd, idle_s, window_s,
                      progress, log)
    write_atomically(out, res)
    return res


def _open_results(out: Path, manifest: BundleManifest, cond: dict, provider: str, threads: int, root: str,
                  log: Callable[[str], None]) -> dict:
    """The results in ``out`` to resume (refused, ProbeError, when they are another bundle's or were
    measured under other conditions), or new, empty ones."""
    if out.exists():
        res = read_results(out)
        if res["bundle"].get("id") != manifest.id:
            raise ProbeError(f"{out}: results of another bundle ({res['bundle'].get('id')}, this one is "
                             f"{manifest.id}): give another --out, or delete it to start over")
        if res["conditions"] != cond:
            raise ProbeError(f"{out}: measured with {res['conditions']}, now asked for {cond}: give another "
                             "--out, or the same options as before to resume")
        log(f"resuming {out}: {len(res['layers'])} layer graphs and "
            f"{sum(len(v) for v in res['stages'].values())} stage graphs already measured")
        return res
    return {"format": RESULTS_FORMAT, "version": VERSION, "bundle": manifest.written,
            "device": device_identity(provider, threads, root), "conditions": cond,
            "layers": {}, "stages": {}, "energy": None}


class _Timing:
    """One probe run's timing of the bundle's graphs into ``res``, in passes: every graph not timed
    yet, then again those timed while a speed check showed the machine slow. Each timing remembers
    the speed check before it (``timed_after``), so that it can be judged again after every pass
    against all checks so far (a machine slowed for a whole pass looks usual until it speeds up)."""

    def __init__(self, res: dict, manifest: BundleManifest, bundle_dir: Path, out: Path, threads: int, provider: str,
                 repeats: int, progress: Callable[[int, int, str], None] | None) -> None:
        self.res, self.manifest, self.bundle_dir, self.out = res, manifest, bundle_dir, out
        self.threads, self.provider, self.repeats, self.progress = threads, provider, repeats, progress
        self.layers, self.cands = manifest.layers, manifest.candidates
        self.what, self.total, self.done = TIMING_GRAPHS, 0, 0
        self.rng = np.random.default_rng(0)
        self.reference, reference_stage = speed_layer(self.layers), speed_stage(self.cands)
        speed = res.setdefault("speed", {"layer": self.reference["id"] if self.reference else None, "ms": [],
                                         "remeasured": 0})
        speed.setdefault("stage", reference_stage["file"] if self.reference and reference_stage else None)
        speed.setdefault("stage_ms", [])
        self.speed = speed
        self.earlier = res.setdefault("earlier", {})   # timings taken while it ran slow, until timed again
        self.timed_after = res.setdefault("timed_after", {})
        self.since_check = SPEED_CHECK_EVERY   # graphs timed since the last speed check
        self.checks = [(fixed_graph_timer(bundle_dir / file, threads, provider), times)
                       for file, times in ((self.reference and self.reference["file"], speed["ms"]),
                                           (speed["stage"], speed["stage_ms"]))
                       if file]

    def start_pass(self, what: str) -> None:
        """Opens a pass: its progress counts the graphs not timed yet (a resumed run's, or those set
        aside to be timed again) from 0. A pass that times nothing says nothing."""
        layers, stages = self.res["layers"], self.res["stages"]
        self.what, self.done = what, 0
        self.total = (sum(item["id"] not in layers for item in self.layers)
                      + sum(g["stage"] not in stages.get(c["key"], {}) for c in self.cands for g in c["graphs"]))
        if self.progress and self.total:
            self.progress(0, self.total, what)

    def tick(self) -> None:
        """One graph timed."""
        self.done += 1
        if self.progress:
            self.progress(self.done, self.total, self.what)

    def check_speed(self) -> float:
        """Times the fixed graphs (and opens a new window of graphs); returns how much slower than
        usual the machine runs now (1 = usual)."""
        self.since_check = 0
        if self.reference is None:
            return 1.0
        for timer, times in self.checks:
            times.append(timer())
        return slowness(self.speed)[-1]

    def before_timing(self, labels: list[str]) -> None:
        """A speed check where a window of graphs is full; then ``labels`` join the current window."""
        if self.since_check >= SPEED_CHECK_EVERY:
            self.check_speed()
        self.since_check += len(labels)
        for label in labels:
            self.timed_after[label] = len(self.speed["ms"]) - 1

    def all_passes(self, remeasure_passes: int, calm_wait_s: float | None, log: Callable[[str], None]) -> None:
        self.start_pass(TIMING_GRAPHS)
        for attempt in range(remeasure_passes + 1):
            self.since_check = SPEED_CHECK_EVERY   # each pass opens with a check
            timed_before = dict(self.timed_after)
            self.one_pass()
            if self.timed_after == timed_before:
                break   # nothing timed in this pass (a finished run, resumed)
            self.check_speed()   # closes the last window
            if self.reference is None or attempt == remeasure_passes:
                break
            slow = set(slow_windows(slowness(self.speed)))
            again = [label for label, j in self.timed_after.items() if j in slow]
            if not again:
                break
            log(f"the machine ran slower for a while ({len(again)} graphs timed then): timing those again")
            set_aside(self.res, again)
            self.start_pass(TIMING_AGAIN)   # before the wait for calm, which is part of the pass
            wait_until_calm(slowness(self.speed)[-1], self.check_speed, 1.0, calm_wait_s)
            self.speed["remeasured"] = self.speed.get("remeasured", 0) + len(again)

    def one_pass(self) -> None:
        """Times every graph of the bundle not timed yet, layers and candidates interleaved."""
        for kind, item in schedule(self.layers, self.cands):
            if kind == "layer":
                self.time_layer(item)
            else:
                self.time_candidate(item)

    def time_layer(self, item: dict) -> None:
        if item["id"] not in self.res["layers"]:
            sess = session(self.bundle_dir / item["file"], self.threads, self.provider)
            feeds = _random_feeds(item["inputs"], self.rng)
            self.before_timing([item["id"]])
            ms = time_call(lambda: sess.run(None, feeds), WARMUP, self.repeats)
            self.res["layers"][item["id"]] = min(ms, self.earlier.pop(item["id"], ms))
            write_atomically(self.out, self.res)
            self.tick()

    def time_candidate(self, item: dict) -> None:
        """Times the candidate's stage graphs not timed yet, in sequence, each fed by the one before."""
        kept = self.res["stages"].setdefault(item["key"], {})
        if all(g["stage"] in kept for g in item["graphs"]):
            return
        start = candidate_inputs(self.manifest, self.rng, item)
        chain = chain_sessions([self.bundle_dir / g["file"] for g in item["graphs"]], self.threads, self.provider)
        runs, new_round = chain_runs(chain, start)
        missing = [g["stage"] not in kept for g in item["graphs"]]
        self.before_timing([f"{item['key']}/{g['stage']}" for g, m in zip(item["graphs"], missing) if m])
        for g, ms in zip(item["graphs"], time_chain(runs, WARMUP, self.repeats, missing, new_round)):
            if ms is not None:
                label = f"{item['key']}/{g['stage']}"
                kept[g["stage"]] = min(ms, self.earlier.pop(label, ms))
                self.tick()
        write_atomically(self.out, self.res)


def _warn_of_drift(res: dict, log: Callable[[str], None]) -> None:
    """Says so when the fixed graphs' timings changed more than ``SPEED_DRIFT_WARN`` over the run."""
    drift = speed_drift(res)
    if drift is not None and drift > SPEED_DRIFT_WARN:
        speed = res["speed"]
        ranges = ", ".join(f"{min(t):.3g}-{max(t):.3g} ms" for t in (speed["ms"], speed["stage_ms"]) if t)
        log(f"note: this machine's speed changed by {drift:.0%} while it was measured (fixed graphs took {ranges}); "
            f"{speed.get('remeasured', 0)} graphs timed while it ran slow were timed again. Another load or "
            "throttling? If the profile disagrees with later measurements, measure again when the machine is idle")


def _probe_energy(res: dict, manifest: BundleManifest, bundle_dir: Path, out: Path, provider: str, threads: int,
                  root: str, vcgencmd: str, idle_s: float, window_s: float,
                  progress: Callable[[int, int, str], None] | None, log: Callable[[str], None]) -> None:
    sensor = find_sensor(root, vcgencmd)
    if sensor is None:
        res["energy"] = {"sensor": None, "note": "no readable power sensor (INA3221 hwmon/iio, Raspberry Pi 5 "
                         "PMIC, hwmon power*_input, RAPL energy_uj; RAPL needs root on most kernels): "
                         "energy not measured"}
        log(res["energy"]["note"])
        return
    cands = manifest.candidates
    if progress:
        progress(0, len(cands), MEASURING_ENERGY)   # the idle power first
    e = res["energy"] if res.get("energy") and res["energy"].get("sensor") else None
    if e is None:
        log(f"power sensor: {sensor.name} ({sensor.what}); idle power for {idle_s:g} s")
        e = {**sensor.describe(), "idle_w": idle_power(sensor, idle_s), "idle_s": idle_s, "window_s": window_s,
             "inferences": {}}
        res["energy"] = e
        write_atomically(out, res)
    rng = np.random.default_rng(1)
    for i, cand in enumerate(cands):
        if cand["key"] not in e["inferences"]:
            sessions = [session(bundle_dir / g["file"], threads, provider) for g in cand["graphs"]]
            io = [([x.name for x in s.get_inputs()], [x.name for x in s.get_outputs()]) for s in sessions]
            start = candidate_inputs(manifest, rng, cand)

            def inference() -> None:
                env = dict(start)
                for s, (ins, outs) in zip(sessions, io):
                    env.update(zip(outs, s.run(outs, {n: env[n] for n in ins})))

            e["inferences"][cand["key"]] = inference_energy(sensor, inference, e["idle_w"], window_s)
            write_atomically(out, res)
        if progress:
            progress(i + 1, len(cands), MEASURING_ENERGY)


def _default_bundle() -> Path:
    archive = Path(__file__).resolve().parents[1]   # probe.pyz, when run from a bundle
    return archive.parent if archive.is_file() else Path.cwd()


# -- command line --------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="probe.pyz", description="Time this bundle's ONNX graphs on this device "
                                 "(and sample its power sensors); fit the results anywhere with "
                                 "`explorer calibrate --fit RESULTS --out PROFILE.yaml`.")
    ap.add_argument("--out", required=True, help="results JSON to write (an existing one is resumed)")
    ap.add_argument("--bundle", default=str(_default_bundle()), help="unpacked bundle folder (default: the one that holds probe.pyz)")
    ap.add_argument("--provider", default=DEFAULT_PROVIDER,
                    help="onnxruntime execution provider (default CPUExecutionProvider; e.g. CUDAExecutionProvider, "
                    "TensorrtExecutionProvider, OpenVINOExecutionProvider, XnnpackExecutionProvider)")
    ap.add_argument("--threads", type=int, default=None, help="intra-op threads (default: all cores)")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per graph (default: the bundle's)")
    ap.add_argument("--no-energy", dest="energy", action="store_false", help="do not sample power sensors")
    ap.add_argument("--idle", type=float, default=2.0, help="seconds of idle power measured first (default 2)")
    ap.add_argument("--window", type=float, default=1.0, help="seconds of back-to-back inferences per "
                    "energy measurement (default 1)")
    ap.add_argument("--sysfs-root", default="/", help="where /sys and /proc are (default /; for tests)")
    ap.add_argument("--vcgencmd", default="vcgencmd", help="the Raspberry Pi's vcgencmd (default: on PATH)")
    args = ap.parse_args(argv)
    try:
        import onnxruntime  # noqa: F401  (checked here: one line, not a traceback, when it is missing)
        if np is None:
            raise ImportError("numpy")
    except ImportError:
        print("probe.pyz: error: needs onnxruntime and numpy: `python3 -m pip install onnxruntime numpy` "
              "(or your board's onnxruntime build)", file=sys.stderr)
        return 2
    last = [0.0]

    def progress(i: int, n: int, what: str) -> None:
        now = time.monotonic()
        if i == n or now - last[0] > 2.0:
            last[0] = now
            print(f"  {what}: {i}/{n}", file=sys.stderr, flush=True)

    try:
        with sigterm_unwinds():   # its scratch folders go with it
            res = run_probe(args.bundle, args.out, args.provider, args.threads, args.repeats, args.energy,
                            args.sysfs_root, args.vcgencmd, args.idle, args.window, progress,
                            log=lambda s: print(s, file=sys.stderr, flush=True))
    except ProbeError as exc:
        print(f"probe.pyz: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"probe.pyz: interrupted; what was measured is in {args.out}: run the same command to go on",
              file=sys.stderr)
        return 130
    d = res["device"]
    print(f"wrote {args.out}: {len(res['layers'])} layer graphs, "
          f"{sum(len(v) for v in res['stages'].values())} stage graphs on {d['cpu']} ({d['provider']}, "
          f"{d['threads']} threads); fit it with `explorer calibrate --fit {args.out} --out myboard.yaml`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
