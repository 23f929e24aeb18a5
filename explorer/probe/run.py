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



from .formats import (DEFAULT_PROVIDER, RESULTS_FORMAT, VERSION, WARMUP, ProbeError, load_manifest, read_results,
                      write_atomically)
from .identity import device_identity
from .power import find_sensor, idle_power, inference_energy
from .sessions import _shared_pool, check_provider, default_threads, session, shared_pool_threads, thread_pool
from .timing import (CALM_WAIT_S, REMEASURE_PASSES, SPEED_CHECK_EVERY, SPEED_DRIFT_WARN, _random_feeds, chain_runs,
                     chain_sessions, fixed_graph_timer, set_aside, slow_windows, slowness, speed_drift, speed_layer,
                     speed_stage, time_call, time_chain, wait_until_calm)


def candidate_inputs(manifest: dict, rng: np.random.Generator, cand: dict | None = None) -> dict[str, np.ndarray]:
    h, w = (cand or {}).get("input_size") or manifest["input_size"]
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
              calm_wait_s: float = CALM_WAIT_S) -> dict:
    """Times every graph of the bundle (single layers, then each candidate's stages in order, each
    fed by the one before), then, where a power sensor is readable, the energy of whole inferences.
    Returns the results, also written (atomically, after every graph) to ``out``. Graphs timed while a
    speed check showed the machine slow are timed again in up to ``remeasure_passes`` more passes, each
    after waiting up to ``calm_wait_s`` for the machine's usual speed."""
    bundle_dir, out = Path(bundle_dir), Path(out)
    manifest = load_manifest(bundle_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    check_provider(provider)
    threads = threads or default_threads()
    _shared_pool(threads)
    threads = shared_pool_threads() or threads
    repeats = repeats or int(manifest["repeats"])
    cond = {"provider": provider, "threads": threads, "thread_pool": thread_pool(),
            "repeats": repeats, "warmup": WARMUP, "statistic": "median", "stage_graphs": "timed in sequence"}
    if out.exists():
        res = read_results(out)
        if res["bundle"].get("id") != manifest["id"]:
            raise ProbeError(f"{out}: results of another bundle ({res['bundle'].get('id')}, this one is "
                             f"{manifest['id']}): give another --out, or delete it to start over")
        if res["conditions"] != cond:
            raise ProbeError(f"{out}: measured with {res['conditions']}, now asked for {cond}: give another "
                             "--out, or the same options as before to resume")
        log(f"resuming {out}: {len(res['layers'])} layer graphs and "
            f"{sum(len(v) for v in res['stages'].values())} stage graphs already measured")
    else:
        res = {"format": RESULTS_FORMAT, "version": VERSION, "bundle": manifest,
               "device": device_identity(provider, threads, root), "conditions": cond,
               "layers": {}, "stages": {}, "energy": None}
    layers, cands = manifest["layers"], manifest["candidates"]
    total = len(layers) + sum(len(c["graphs"]) for c in cands)
    done = 0

    def tick(what: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, what)

    rng = np.random.default_rng(0)
    reference, reference_stage = speed_layer(layers), speed_stage(cands)
    speed = res.setdefault("speed", {"layer": reference["id"] if reference else None, "ms": [], "remeasured": 0})
    speed.setdefault("stage", reference_stage["file"] if reference and reference_stage else None)
    speed.setdefault("stage_ms", [])
    earlier = res.setdefault("earlier", {})   # timings taken while it ran slow, until timed again
    # each kept timing's speed check before it: judged again after every pass against all checks so
    # far (a machine slowed for a whole pass looks usual until it speeds up)
    timed_after = res.setdefault("timed_after", {})
    since_check = [SPEED_CHECK_EVERY]   # graphs timed since the last speed check
    checks = [(fixed_graph_timer(bundle_dir / file, threads, provider), times)
              for file, times in ((reference and reference["file"], speed["ms"]), (speed["stage"], speed["stage_ms"]))
              if file]

    def check_speed() -> float:
        """Times the fixed graphs (and opens a new window of graphs); returns how much slower than
        usual the machine runs now (1 = usual)."""
        since_check[0] = 0
        if reference is None:
            return 1.0
        for timer, times in checks:
            times.append(timer())
        return slowness(speed)[-1]

    def measure(sess, feeds, label: str) -> float:
        if since_check[0] >= SPEED_CHECK_EVERY:
            check_speed()
        since_check[0] += 1
        timed_after[label] = len(speed["ms"]) - 1
        ms = time_call(lambda: sess.run(None, feeds), WARMUP, repeats)
        return min(ms, earlier.pop(label, ms))

    for attempt in range(remeasure_passes + 1):
        since_check[0] = SPEED_CHECK_EVERY   # each pass opens with a check
        timed_before = dict(timed_after)
        for kind, item in schedule(layers, cands):
            if kind == "layer":
                if item["id"] not in res["layers"]:
                    sess = session(bundle_dir / item["file"], threads, provider)
                    res["layers"][item["id"]] = measure(sess, _random_feeds(item["inputs"], rng), item["id"])
                    write_atomically(out, res)
                tick("layers")
                continue
            kept = res["stages"].setdefault(item["key"], {})
            if all(g["stage"] in kept for g in item["graphs"]):
                for _ in item["graphs"]:
                    tick("stages")
                continue
            start = candidate_inputs(manifest, rng, item)
            chain = chain_sessions([bundle_dir / g["file"] for g in item["graphs"]], threads, provider)
            runs, new_round = chain_runs(chain, start)
            missing = [g["stage"] not in kept for g in item["graphs"]]
            labels = [f"{item['key']}/{g['stage']}" for g, m in zip(item["graphs"], missing) if m]
            if since_check[0] >= SPEED_CHECK_EVERY:
                check_speed()
            since_check[0] += len(labels)
            for label in labels:
                timed_after[label] = len(speed["ms"]) - 1
            for g, ms in zip(item["graphs"], time_chain(runs, WARMUP, repeats, missing, new_round)):
                if ms is not None:
                    label = f"{item['key']}/{g['stage']}"
                    kept[g["stage"]] = min(ms, earlier.pop(label, ms))
                tick("stages")
            write_atomically(out, res)
        if timed_after == timed_before:
            break   # nothing timed in this pass (a finished run, resumed)
        check_speed()   # closes the last window
        if reference is None or attempt == remeasure_passes:
            break
        slow = set(slow_windows(slowness(speed)))
        again = [label for label, j in timed_after.items() if j in slow]
        if not again:
            break
        log(f"the machine ran slower for a while ({len(again)} graphs timed then): timing those again")
        wait_until_calm(slowness(speed)[-1], check_speed, 1.0, calm_wait_s)
        set_aside(res, again)
        speed["remeasured"] = speed.get("remeasured", 0) + len(again)
        done -= len(layers) + sum(len(c["graphs"]) for c in cands)   # the progress bar goes round again
    write_atomically(out, res)
    drift = speed_drift(res)
    if drift is not None and drift > SPEED_DRIFT_WARN:
        ranges = ", ".join(f"{min(t):.3g}-{max(t):.3g} ms" for t in (speed["ms"], speed["stage_ms"]) if t)
        log(f"note: this machine's speed changed by {drift:.0%} while it was measured (fixed graphs took {ranges}); "
            f"{speed.get('remeasured', 0)} graphs timed while it ran slow were timed again. Another load or "
            "throttling? If the profile disagrees with later measurements, measure again when the machine is idle")
    if energy:
        _probe_energy(res, manifest, bundle_dir, out, provider, threads, root, vcgencmd, idle_s, window_s,
                      progress, log)
    write_atomically(out, res)
    return res


def _probe_energy(res: dict, manifest: dict, bundle_dir: Path, out: Path, provider: str, threads: int,
                  root: str, vcgencmd: str, idle_s: float, window_s: float,
                  progress: Callable[[int, int, str], None] | None, log: Callable[[str], None]) -> None:
    sensor = find_sensor(root, vcgencmd)
    if sensor is None:
        res["energy"] = {"sensor": None, "note": "no readable power sensor (INA3221 hwmon/iio, Raspberry Pi 5 "
                         "PMIC, hwmon power*_input, RAPL energy_uj; RAPL needs root on most kernels): "
                         "energy not measured"}
        log(res["energy"]["note"])
        return
    e = res["energy"] if res.get("energy") and res["energy"].get("sensor") else None
    if e is None:
        log(f"power sensor: {sensor.name} ({sensor.what}); idle power for {idle_s:g} s")
        e = {**sensor.describe(), "idle_w": idle_power(sensor, idle_s), "idle_s": idle_s, "window_s": window_s,
             "inferences": {}}
        res["energy"] = e
        write_atomically(out, res)
    cands = manifest["candidates"]
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
            progress(i + 1, len(cands), "energy")


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
