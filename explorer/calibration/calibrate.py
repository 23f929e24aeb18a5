"""``explorer calibrate``: a sweep of single-layer graphs and the stage graphs of a few candidates,
timed with onnxruntime on the device (the probe, ``explorer.probe``) and fitted to a CPU-style
profile. The graphs travel in a bundle (``bundle.py``) so the device needs no torch; run in one
process, ``calibrate`` is bundle + probe + fit on this machine."""

from __future__ import annotations

import dataclasses
import datetime
import platform
from pathlib import Path
from typing import Callable

import numpy as np

from explorer import probe as _probe
from explorer.calibration.bundle import write_bundle_dir
from explorer.calibration.measure import conditions
from explorer.calibration.results_schema import check_results
from explorer.calibration.sweep import (  # noqa: F401
    DEFAULT_COUNTS,
    HOST_KINDS,
    STAGE_SIZES,
    SweepLayer,
    layer_graph,
    sweep_layers,
)
from explorer.cost import candidate_cost
from explorer.cost.devices import DeviceProfile, KindCost
from explorer.cost.fit import (
    MEMORY_KINDS,
    Observation,
    errors,
    fit_profile,
    fit_summary,
)
from explorer.cost.precision import workload_quantized
from explorer.cost.workloads import KINDS, Workload
from explorer.errors import UserError
from explorer.files import scratch_dir
from explorer.probe import DEFAULT_PROVIDER
from explorer.space import Candidate


def fit_host(measured: list[tuple[Workload, float]], name: str = "host",
             description: str | None = None, cond: dict | None = None,
             stage_obs: list[Observation] = (), energy: dict | None = None,
             source: str | None = None) -> DeviceProfile:
    """A CPU-style profile fitted to single-layer and stage timings;
    with ``energy`` (the probe's energy section), also its fixed energy and active power."""
    obs = [Observation(w.layer, [w], ms, stages=1) for w, ms in measured] + list(stage_obs)
    base = DeviceProfile(
        name=name, description=description or f"{platform.node() or 'this machine'} CPU, onnxruntime",
        overlap=False, bandwidth_gbs=10.0, kinds={k: KindCost(20.0, 0.005) for k in HOST_KINDS},
        stage_overhead_ms=0.02)
    ident = {k: k for k in HOST_KINDS}
    rate_of = {k: k for k in ("conv", "pointwise", "pointwise_1ch", "depthwise", "conv1d", "resize", "bilinear")}

    def fit(start: DeviceProfile, overlap: bool, exponent: float) -> DeviceProfile:
        return fit_profile(dataclasses.replace(start, overlap=overlap, body_exponent=exponent), obs, rate_of, ident,
                           free_inference=False, free_stage=True, own_bandwidth=HOST_KINDS)

    best, best_err = None, None
    for overlap in (False, True):
        p = fit(base, overlap, 1.0)
        err = float(errors(p, obs)["error"].abs().median())
        if best_err is None or err < best_err:
            best, best_err = p, err
    # The body exponent is chosen on the stage graphs alone, measured at several input sizes: the one
    # that leaves the least difference in bias between sizes (the single-layer graphs, each with its
    # own layout conversions, would pull it elsewhere). A fine grid with no margin for 1: a jump from
    # 1 to 1.2 between two calibrations of one machine moved their predictions apart by 6-7%.
    if len({o.group for o in stage_obs}) > 1:
        fitted = {e: best if e == 1.0 else fit(best, best.overlap, e) for e in BODY_EXPONENTS}   # warm starts
        spread = {e: _size_bias_spread(p, list(stage_obs)) for e, p in fitted.items()}
        best = fitted[min(spread, key=spread.get)]
    layers = errors(best, obs[:len(measured)])
    summary = [fit_summary(layers, f"{len(measured)} single-layer graphs measured here")]
    if stage_obs:
        summary.append(fit_summary(errors(best, list(stage_obs)), f"{len(stage_obs)} stage graphs of "
                                   "random candidates measured here"))
    per_kind = {k: round(float(layers[[w.kind == k for w, _ in measured]]["error"].abs().median()), 4)
                for k in HOST_KINDS if any(w.kind == k for w, _ in measured)}
    cond = cond or conditions()
    provenance = {
        "calibrated": True, "latency": "measured",
        "sources": [source or f"explorer calibrate on {platform.node()} at "
                    f"{datetime.datetime.now().isoformat(timespec='seconds')}"],
        "conditions": cond, "provider": cond.get("provider", DEFAULT_PROVIDER),
        "fit": summary, "median_abs_error_per_kind": per_kind, "checks": []}
    fixed_j, power_w, energy_prov = fit_energy(energy)
    provenance.update(energy_prov)
    return dataclasses.replace(best, energy_fixed_j=fixed_j, active_power_w=power_w, provenance=provenance)


#: Body exponents ``fit_host`` chooses from (see ``DeviceProfile.body_exponent``).
BODY_EXPONENTS = tuple(round(0.95 + 0.025 * i, 3) for i in range(11))   # 0.95 ... 1.2


def _size_bias_spread(profile: DeviceProfile, stage_obs: list[Observation]) -> float:
    """Largest minus smallest median log error among the groups (input sizes) of the stage graphs."""
    by_group: dict[str, list[float]] = {}
    for row, o in zip(errors(profile, stage_obs).itertuples(), stage_obs):
        by_group.setdefault(o.group, []).append(float(np.log1p(row.error)))
    medians = [float(np.median(v)) for v in by_group.values()]
    return max(medians) - min(medians)


def fit_energy(energy: dict | None) -> tuple[float, float, dict]:
    """(fixed J, active W, provenance) from the probe's energy section: E = fixed + P x t, least
    squares over whole inferences of the calibration candidates, both terms kept >= 0."""
    if not energy or not energy.get("sensor") or not energy.get("inferences"):
        note = (energy or {}).get("note") or "energy not measured (the probe ran without --energy)"
        return 0.0, 0.0, {"energy": "not measured", "energy_note": f"{note}; the profile prices no energy (0 J)"}
    runs = list(energy["inferences"].values())
    t = np.array([r["ms"] for r in runs]) / 1000.0
    e = np.array([r["j"] for r in runs])
    if len(runs) >= 2 and np.ptp(t) > 0:
        power, fixed = np.polyfit(t, e, 1)
    else:
        power, fixed = 0.0, -1.0
    if fixed < 0:
        fixed, power = 0.0, float(np.dot(e, t) / max(np.dot(t, t), 1e-12))
    if power < 0:
        fixed, power = float(e.mean()), 0.0
    pred = fixed + power * t
    err = np.abs(pred / np.where(e > 0, e, np.nan) - 1)
    return float(fixed), float(power), {
        "energy": "measured",
        "energy_sensor": {k: energy[k] for k in ("sensor", "kind", "what")},
        "energy_note": f"E = {fixed:.4g} J + {power:.4g} W x t over {len(runs)} whole inferences, idle "
                       f"{energy['idle_w']:.3g} W subtracted",
        "energy_fit": {"count": len(runs), "median_abs_error": round(float(np.nanmedian(err)), 4)
                       if np.isfinite(err).any() else None}}


def read_results(path: str | Path) -> dict:
    """A probe results file, checked whole (``results_schema``): one line, exit 2, for a truncated,
    foreign or hand-edited file."""
    try:
        data = _probe.read_results(Path(path))
    except _probe.ProbeError as exc:
        raise UserError(str(exc)) from None
    return check_results(data, path)


def _observations(results: dict) -> dict[str, list]:
    """A probe run's timings: "layers" and "layers_int8" ((workload, ms, the probe's label) each),
    "stages" and "stages_int8" (``Observation``s labelled as the probe labels them)."""
    bundle = results["bundle"]
    obs: dict[str, list] = {"layers": [], "layers_int8": [], "stages": [], "stages_int8": []}
    for layer in bundle["layers"]:
        if layer["id"] in results["layers"]:
            w = dict(layer["workload"])
            w["in_shape"], w["out_shape"] = tuple(w["in_shape"]), tuple(w["out_shape"])
            into = obs["layers_int8"] if layer.get("precision") == "int8" else obs["layers"]
            into.append((Workload(**w), float(results["layers"][layer["id"]]), layer["id"]))
    for cand in bundle["candidates"]:
        kept = results["stages"].get(cand["key"], {})
        if not kept:
            continue
        size = tuple(cand.get("input_size", bundle["input_size"]))
        cost = candidate_cost(Candidate.from_dict(cand["candidate"]), size)
        into = obs["stages_int8"] if cand.get("precision") == "int8" else obs["stages"]
        for stage, ms in kept.items():   # a stage, or (int8 deployments) stages joined by '+'
            wl = [w for w in cost.workloads if w.stage in stage.split("+")]
            into.append(Observation(f"{cand['key']}/{stage}", wl, float(ms), weight=4.0, stages=1,
                                    group=f"{size[0]}x{size[1]}"))
    return obs


def fit_results(results: dict, name: str = "host", source: str | None = None) -> DeviceProfile:
    """The profile a probe run gives: the same fit ``explorer calibrate`` makes."""
    bundle = results["bundle"]
    obs = _observations(results)
    measured = [(w, ms) for w, ms, _ in obs["layers"]]
    measured_int8 = [(w, ms) for w, ms, _ in obs["layers_int8"]]
    stage_obs, stage_obs_int8 = obs["stages"], obs["stages_int8"]
    if len(measured) < len(KINDS):
        raise UserError(f"the results hold {len(measured)} measured layer graphs, too few to fit: let the probe "
                        "finish (run it again with the same --out to go on)")
    dev = results["device"]
    c = results["conditions"]
    cond = {"onnxruntime": dev["onnxruntime"], "provider": c["provider"], "threads": c["threads"],
            "thread_pool": c.get("thread_pool", "per-session"),
            "repeats": c["repeats"], "warmup": c["warmup"], "statistic": c["statistic"],
            "machine": dev["machine"], "processor": dev["cpu"], "cores": dev["cores"],
            **({"board": dev["board"]} if dev.get("board") else {}), "bundle": bundle["id"]}
    drift = _probe.speed_drift(results)
    if drift is not None:   # how much the machine's own speed changed while it was measured
        cond["speed_drift"] = round(drift, 3)
    remeasured = (results.get("speed") or {}).get("remeasured")
    if remeasured:   # graphs timed while it ran slow, and timed again
        cond["speed_remeasured"] = remeasured
    outliers = (results.get("speed") or {}).get("retimed_outliers")
    if outliers:   # graphs far above the fit of the others, timed again (``slow_outliers``)
        cond["retimed_outliers"] = outliers
    where = dev.get("board") or dev.get("host") or "a device"
    description = f"{where}: {dev['cpu']}, onnxruntime {dev['onnxruntime']} {c['provider']}, {c['threads']} threads"
    profile = fit_host(measured, name=name, description=description, cond=cond, stage_obs=stage_obs,
                       energy=results.get("energy"),
                       source=source or f"probe on {dev.get('host') or where} (bundle {bundle['id']}), fitted at "
                       f"{datetime.datetime.now().isoformat(timespec='seconds')}")
    return with_int8(profile, measured, measured_int8, stage_obs_int8)


def with_int8(profile: DeviceProfile, measured: list[tuple[Workload, float]],
              measured_int8: list[tuple[Workload, float]], stage_obs: list[Observation] = ()) -> DeviceProfile:
    """``profile`` with an int8 section fitted on ``stage_obs``, stage graphs quantized whole as
    ``explorer export --quantize int8`` quantizes them, starting from ``profile`` itself: only the rates,
    overheads and memory rates of the quantized and memory-bound kinds move, and the fit's prior holds
    what the int8 graphs barely show at its fp32 value; per-inference and per-stage costs are the fp32
    ones. Fitted from scratch on the quantized single-layer graphs and the int8 stage graphs, the int8
    rates came out different by orders of magnitude from one calibration of a machine to the next, and
    held-out int8 stage graphs were predicted worse than when fitted so: a
    single-layer graph quantized alone pays the quantize, layout changes and dequantize that a
    whole-quantized graph pays once at its edges, and says little about the graph. Results
    without int8 stage graphs get the from-scratch fit on the single-layer ones, with the fp32
    timings of the kinds they lack. Unchanged when no quantized pointwise convolution was measured."""
    measured_int8 = [(w, ms) for w, ms in measured_int8 if workload_quantized(w)]
    kinds = {w.kind for w, _ in measured_int8}
    if "pointwise" not in kinds:
        return profile
    fp32 = dataclasses.replace(profile, int8=None)
    if stage_obs:
        moved = tuple(sorted(kinds)) + tuple(k for k in MEMORY_KINDS if k not in kinds)
        fitted = fit_profile(fp32, list(stage_obs), {k: k for k in sorted(kinds)}, {k: k for k in moved},
                             free_bandwidth=False, free_inference=False, own_bandwidth=moved)
    else:
        floats = [(w, ms) for w, ms in measured if w.kind not in kinds]
        fitted = fit_host(measured_int8 + floats, name=profile.name, cond=profile.provenance.get("conditions"))
    layers = errors(fitted, [Observation(w.layer, [w], ms, stages=1) for w, ms in measured_int8])
    summary = [fit_summary(layers, f"{len(measured_int8)} int8 (static QDQ) single-layer graphs measured here")]
    if stage_obs:
        summary.append(fit_summary(errors(fitted, list(stage_obs)), f"{len(stage_obs)} int8 deployed stage graphs "
                                   "(each quantized whole) of random candidates measured here"))
    int8 = dataclasses.replace(
        fitted, description=profile.description, inference_overhead_ms=profile.inference_overhead_ms,
        stage_overhead_ms=profile.stage_overhead_ms, energy_fixed_j=profile.energy_fixed_j,
        active_power_w=profile.active_power_w,
        provenance={"fit": summary,
                    "note": "stage graphs quantized whole, as `explorer export --quantize int8` quantizes them; "
                            "an int8 candidate's stage graph is priced at fp32 where int8 would not be at least "
                            "5% faster (such an export keeps it fp32)"})
    return dataclasses.replace(profile, int8=int8)


def calibrate(threads: int | None = None, repeats: int = 25, seed: int = 0, scale: float = 1.0,
              progress: Callable[[str, int, int | None], None] | None = None, name: str = "host",
              stage_candidates: int | None = None, exclude: set[str] = frozenset(),
              provider: str = DEFAULT_PROVIDER, energy: bool = True, sysfs_root: str = "/",
              log: Callable[[str], None] = lambda s: None, results_out: Path | None = None,
              bundle_out: Path | None = None, remeasure_passes: int = _probe.REMEASURE_PASSES,
              calm_wait_s: float | None = None) -> DeviceProfile:
    """Bundle, probe and fit in one process (the numbers a separate probe run would give): layer
    sweep plus the stages of ``stage_candidates`` random default-space candidates (none of
    ``exclude``, candidate keys). ``results_out`` / ``bundle_out``: also keep the probe's results /
    the bundle there. ``remeasure_passes``, ``calm_wait_s``: the probe's (``run_probe``; None: its own default).
    ``progress(what, done, total)``: each phase of the work counted from 0 to its own total (None until
    it is known), called with 0 when it starts: ``EXPORTING``, the probe's (``TIMING_GRAPHS``, each
    pass of ``TIMING_AGAIN``, ``MEASURING_ENERGY``), and ``FITTING`` before each round of graphs far
    above the fit is timed again (``TIMING_AGAIN``) and before the profile is returned."""
    report = progress or (lambda what, done, total: None)
    try:
        _probe.check_provider(provider)
    except _probe.ProbeError as exc:
        raise UserError(str(exc)) from None
    with scratch_dir("calibrate") as tmp:
        folder = bundle_out or Path(tmp) / "bundle"
        report(EXPORTING, 0, None)   # how many graphs: known once the sweep is drawn
        write_bundle_dir(folder, scale=scale, seed=seed, n_stage=stage_candidates, exclude=exclude,
                         repeats=repeats, progress=lambda i, n: report(EXPORTING, i, n))
        out = results_out or Path(tmp) / "results.json"
        try:
            results = _probe.run_probe(folder, out, provider, threads, repeats, energy, sysfs_root,
                                       progress=lambda i, n, what: report(what, i, n), log=log,
                                       remeasure_passes=remeasure_passes, calm_wait_s=calm_wait_s)
            results = _retime_outliers(results, folder, out, provider, threads, repeats, sysfs_root, report, log)
        except _probe.ProbeError as exc:
            raise UserError(str(exc)) from None
    report(FITTING, 0, 1)
    profile = fit_results(results, name=name, source=f"explorer calibrate on {platform.node()} at "
                          f"{datetime.datetime.now().isoformat(timespec='seconds')}")
    report(FITTING, 1, 1)
    return profile


#: ``calibrate``'s own phases (``progress``'s ``what``), beside the probe's
EXPORTING, FITTING = "exporting graphs", "fitting"


def _retime_outliers(results: dict, folder: Path, out: Path, provider: str, threads: int | None, repeats: int,
                     sysfs_root: str, report: Callable[[str, int, int | None], None],
                     log: Callable[[str], None]) -> dict:
    """Up to ``RETIME_ROUNDS`` rounds: the graphs ``slow_outliers`` finds are timed again, each keeping
    its faster timing (none a third time that kept ``SETTLED`` of its time the second)."""
    settled: set[str] = set()   # timed again without getting faster: the fit's misses, not the machine's
    for _ in range(RETIME_ROUNDS):
        report(FITTING, 0, 1)
        slow = [label for label in slow_outliers(fit_results(results), results) if label not in settled]
        report(FITTING, 1, 1)
        if not slow:
            break
        log(f"{len(slow)} graphs took {1 + RETIME_ABOVE:.2f}x or more of what the fit of all the others "
            "predicts: timing those again")
        before = {label: _timing(results, label) for label in slow}
        _probe.set_aside(results, slow)
        speed = results["speed"]
        speed["retimed_outliers"] = speed.get("retimed_outliers", 0) + len(slow)
        _probe.write_atomically(out, results)
        # those graphs once more each: the round itself is their second timing
        results = _probe.run_probe(folder, out, provider, threads, repeats, False, sysfs_root,
                                   progress=lambda i, n, what: report(_probe.TIMING_AGAIN, i, n), log=log,
                                   remeasure_passes=0, again=True)
        settled |= {label for label, ms in before.items() if _timing(results, label) > SETTLED * ms}
    return results


#: After the probe, graphs whose timing is this much above what the fit of all the timings predicts
#: are timed again (``RETIME_ROUNDS`` times at most), and each keeps its faster timing. A machine
#: shared with other loads can be slowed between two of the probe's speed checks without either
#: showing it: on a machine that ran 1x or 2x slow by turns, every few seconds, about a third of the
#: layer graphs and a fifth of the stage graphs of one calibration were 20% or more above the fit.
RETIME_ABOVE = 0.2
RETIME_ROUNDS = 2
#: A graph whose second timing kept more than this fraction of its first is not timed a third time:
#: it is slow for the fit, not for the machine. On a calm machine whose layer graphs the fit prices
#: poorly, hundreds of graphs per calibration can lie 20% or more above the fit, and each round would
#: time them all again.
SETTLED = 0.9


def _timing(results: dict, label: str) -> float:
    key, _, stage = label.partition("/")
    return float(results["stages"][key][stage] if stage else results["layers"][key])


def slow_outliers(profile: DeviceProfile, results: dict) -> list[str]:
    """The probe's labels of the graphs in ``results`` that took ``RETIME_ABOVE`` or more longer than
    ``profile`` predicts (the int8 ones against its int8 section)."""
    obs = _observations(results)
    int8 = profile.int8 or profile
    slow = []
    for prof, layers, stages in ((profile, obs["layers"], obs["stages"]),
                                 (int8, obs["layers_int8"], obs["stages_int8"])):
        labelled = [Observation(label, [w], ms, stages=1) for w, ms, label in layers] + list(stages)
        if labelled:
            frame = errors(prof, labelled)
            slow += [str(label) for label, e in zip(frame["what"], frame["error"]) if e < 1 / (1 + RETIME_ABOVE) - 1]
    return slow
