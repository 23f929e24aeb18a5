"""Timing graphs and chains of graphs, and the speed checks that tell when the machine ran slow."""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Callable, Iterable, Sequence

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None


from .formats import DEFAULT_PROVIDER, WARMUP
from .rewrites import _onnx, hand_off_blocked, hand_off_channels_last
from .scratch import scratch_dir
from .sessions import session

def _random_feeds(inputs: Iterable[dict], rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {i["name"]: rng.random(tuple(i["shape"]), dtype=np.float32) for i in inputs}


def chain_sessions(models: Sequence["bytes | Path"], threads: "int | None" = None,
                   provider: str = DEFAULT_PROVIDER) -> list:
    """Sessions (``session``) for graphs that run one after another and feed each other by tensor name,
    as the runtime runs a model's stage graphs: on the CPU provider, where this Python has ``onnx``, a
    tensor that one graph outputs and the next converts into the blocked layout is handed over blocked
    (``hand_off_blocked``; its name then ends in ``SUFFIX``), and one that it makes channels-last and the
    next transposes channels-last again, channels-last (``hand_off_channels_last``). What the probe and
    the held-out timings time a candidate's stage graphs with: timed alone, each stage paid the layout
    conversions at its edges that the runtime does not, and the host profile predicted the paper
    design's paths too slow."""
    if provider != DEFAULT_PROVIDER or _onnx() is None:
        return [session(m, threads, provider) for m in models]
    with scratch_dir("chain") as tmp:
        sessions = [session(m, threads, provider, save_optimized=Path(tmp) / f"{k}.onnx") for k, m in enumerate(models)]
        try:
            graphs = [_onnx().load(str(Path(tmp) / f"{k}.onnx")) for k in range(len(models))]
            ins = [[i.name for i in s.get_inputs()] for s in sessions]
            outs = [[o.name for o in s.get_outputs()] for s in sessions]
            handed = hand_off_blocked(graphs, ins, outs) + hand_off_channels_last(graphs, ins, outs)
        except Exception:   # an onnxruntime whose optimised graphs the rewrite does not know
            return sessions
    if not handed:
        return sessions
    return [session(g.SerializeToString(), threads, provider, optimize=False) for g in graphs]


def time_call(fn: Callable[[], object], warmup: int = WARMUP, repeats: int = 15) -> float:
    """Median wall time of ``fn`` in ms after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(samples)


def time_chain(fns: Sequence[Callable[[], object]], warmup: int = WARMUP, repeats: int = 15,
               timed: "Sequence[bool] | None" = None,
               new_round: "Callable[[], object] | None" = None) -> "list[float | None]":
    """Median wall time in ms of each of ``fns`` (those ``timed``; None for the others), called in order
    ``warmup`` rounds untimed, then ``repeats`` rounds timed, ``new_round`` (untimed) before each: a
    model's stage graphs as the runtime runs them, one after another, each reading what the one before
    it wrote. Timed each on its own, over and over, the paper design's 12 stage graphs take less in
    all than in sequence (the small ones, exit heads and the fusion unit, much less), and a profile
    fitted to such timings predicts the runtime's paths too fast."""
    timed = list(timed) if timed is not None else [True] * len(fns)
    for _ in range(warmup):
        if new_round is not None:
            new_round()
        for fn in fns:
            fn()
    samples: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        if new_round is not None:
            new_round()
        for fn, kept in zip(fns, samples):
            t0 = time.perf_counter()
            fn()
            kept.append((time.perf_counter() - t0) * 1000.0)
    return [statistics.median(t) if on else None for t, on in zip(samples, timed)]


def chain_runs(chain: list, start: dict) -> "tuple[list[Callable[[], object]], Callable[[], object]]":
    """One call per session of ``chain``, each reading its inputs from what ``start`` and the sessions
    before it hold, and the call that starts a new round from ``start``."""
    env = dict(start)

    def run(sess, ins, outs) -> None:
        env.update(zip(outs, sess.run(outs, {n: env[n] for n in ins})))

    def new_round() -> None:
        env.clear()
        env.update(start)
    return ([lambda s=s, i=[x.name for x in s.get_inputs()], o=[x.name for x in s.get_outputs()]: run(s, i, o)
             for s in chain], new_round)


#: The probe times two fixed graphs first, again after every this many graphs, and last: how much
#: the machine's own speed changed while it measured (another load, throttling), and when.
SPEED_CHECK_EVERY = 12
SPEED_CHECK_REPEATS = 9
#: Graphs timed between two speed checks of which one ran this much slower than the machine's usual
#: speed (``usual_speed``: a shared machine is slowed more often than sped up) are timed again (at
#: most ``REMEASURE_PASSES`` times), once a check shows it back to its usual speed (waiting up to
#: ``CALM_WAIT_S``): a load that came and went leaves no mark.
SLOW = 0.10
REMEASURE_PASSES = 3
CALM_WAIT_S = 60.0
#: A change of speed above this fraction while measuring is reported.
SPEED_DRIFT_WARN = 0.10


def speed_layer(layers: list[dict]) -> "dict | None":
    """The layer graph the probe re-times to follow the machine's speed: the largest float pointwise
    convolution (every thread busy for long enough that a competing load shows)."""
    pointwise = [layer for layer in layers if layer.get("precision", "fp32") == "fp32"
                 and layer["workload"]["kind"] == "pointwise"]
    return max(pointwise, key=lambda layer: layer["workload"]["macs"]) if pointwise else None


def speed_stage(cands: list[dict]) -> "dict | None":
    """The stage graph the probe also re-times: the first candidate's image encoder (about a
    millisecond of mixed operators, which another load slows more than one large convolution)."""
    graphs = cands[0]["graphs"] if cands else []
    return next((g for g in graphs if g["stage"] == "image_encoder"), graphs[0] if graphs else None)


def speed_drift(results: dict) -> "float | None":
    """(slowest / fastest) - 1 of the probe's speed checks (``slowness``), None with fewer than two."""
    ratios = slowness(results.get("speed") or {})
    return max(ratios) / min(ratios) - 1.0 if len(ratios) >= 2 else None


def usual_speed(checks: list[float]) -> float:
    """The time a speed check takes on this machine undisturbed: the 10th percentile of the checks
    (a shared machine was seen slowed for most of a calibration, its first quartile 14% slow)."""
    return float(np.percentile(checks, 10))


def slowness(speed: dict) -> list[float]:
    """Per speed check, how much slower than usual the machine ran (1 = usual; the slower graph's)."""
    series = [speed.get("ms") or []]
    if len(speed.get("stage_ms") or []) == len(series[0]):
        series.append(speed["stage_ms"])
    ratios = [[ms / usual_speed(s) for ms in s] for s in series if s]
    return [max(r) for r in zip(*ratios)]


def wait_until_calm(latest: float, time_again: Callable[[], float], usual: float,
                    wait_s: float | None = None) -> float:
    """While the fixed graph's ``latest`` time is ``SLOW`` or more above ``usual``, waits a second and
    times it again (``time_again``), for at most ``wait_s`` (None: ``CALM_WAIT_S``, read when called);
    returns its last time."""
    calm_by = time.monotonic() + (CALM_WAIT_S if wait_s is None else wait_s)
    while latest > usual * (1 + SLOW) and time.monotonic() < calm_by:
        time.sleep(1.0)   # still slow: give the other load time to finish
        latest = time_again()
    return latest


def fixed_graph_timer(graph: Path, threads: int, provider: str) -> Callable[[], float]:
    """Times one of the speed checks' fixed graphs (``SPEED_CHECK_REPEATS`` runs, median ms), fed as
    the probe feeds it, so that another process can tell how fast the machine runs against a probe's
    checks (``usual_speed`` of its ``speed`` series)."""
    sess = session(graph, threads, provider)
    feeds = _random_feeds(({"name": i.name, "shape": i.shape} for i in sess.get_inputs()), np.random.default_rng(0))
    return lambda: time_call(lambda: sess.run(None, feeds), WARMUP, SPEED_CHECK_REPEATS)


def slow_windows(ratios: list[float]) -> list[int]:
    """Indices j of the windows between check j and check j + 1 (the graphs timed in between) that
    either check shows the machine ``SLOW`` or more slower than usual (``ratios``: ``slowness``)."""
    slow = [x > 1 + SLOW for x in ratios]
    return [j for j in range(len(slow) - 1) if slow[j] or slow[j + 1]]


def set_aside(res: dict, labels: Iterable[str]) -> None:
    """Moves the timings of the graphs ``labels`` (layer ids, or "candidate/stage") from ``res`` to
    its ``earlier`` ones: a probe run on ``res`` times them again and keeps the faster timing."""
    earlier = res.setdefault("earlier", {})
    for label in labels:
        key, _, stage = label.partition("/")
        earlier[label] = res["stages"][key].pop(stage) if stage else res["layers"].pop(key)

