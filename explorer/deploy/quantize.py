"""int8 deployment: an exported model's stage graphs quantized statically with onnxruntime
(QDQ format: int8 weights per output channel, uint8 activations whose ranges are calibrated on
frames of a data set), and every path's metrics measured again after quantization.

Each stage graph is calibrated on the inputs it really receives: the float model runs the
calibration frames and every stage's inputs are kept. A stage graph is quantized whole: every operator
onnxruntime's quantizer handles (convolutions of every kind, resizes, additions, concatenations), so
that its tensors stay uint8 from one layer to the next and it quantizes and dequantizes only at its
edges; only the LiDAR encoder stays fp32 (``FLOAT_STAGES``). Quantizing only the wide convolutions,
with float depthwise layers between them, paid for nothing: the encoder stage then ran hardly faster
than in fp32, where quantized whole it runs much faster. The decoder stays channels-last, as onnxruntime runs quantized
convolutions: its nearest up-sampling becomes a uint8 copy done so (``upsamples_channels_last``; a
Resize left to onnxruntime is kept channels-first, ``resizes_kept_nchw``, its channels-last uint8
kernel being far slower) and its skip additions add so (``explorer.probe.channels_last_skip_adds``).
Whole quantization does not pay everywhere: on some CPUs the full-resolution decoders 3-4 run no
faster in int8 alone (onnxruntime's uint8 depthwise kernels can be slower than its blocked fp32 ones;
bench_int8_layers times each kind of layer in both precisions).
So an export keeps a stage int8 only
where int8 saves the staged runtime at least ``1 - INT8_KEEP_RATIO`` of that stage's fp32 time on the
exporting machine, with int8 neighbours handing each other uint8 tensors (``compare_speed``;
``stages="all"``: every stage int8), and the cost model
prices an int8 candidate's stages the same way (``explorer.cost.devices``); then, where a path loses
more RMSE than the export allows, it gives graphs back to fp32 one by one. Path 0 (the scan) has
nothing to quantize.

Weights are quantized to 7 bits (``reduce_range``): x86 CPUs without VNNI multiply uint8 by int8 in
pairs summed into int16 (VPMADDUBSW), which saturates with full-range weights: on an AVX2 CPU
without VNNI, full range degraded the paper design's last path by 29% RMSE, 7 bits by under 2%.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Callable

import numpy as np

from explorer.cost.precision import INT8_KEEP_RATIO
from explorer.data import open_dataset, require_scores
from explorer.deploy import runtime
from explorer.deploy.int8_graphs import quantize_graph, share_edge_scales
from explorer.deploy.manifest import (MANIFEST, Frames, Manifest, PathMetrics, QuantizationRecord, StageTiming,
                                      read_manifest, write_manifest)
from explorer.deploy.runtime import AnytimeRunner
from explorer.errors import UserError
from explorer.probe import chain_runs, time_chain

#: ``explorer export --int8-stages``: which stages of an int8 export are int8
INT8_STAGES = ("faster", "all")


#: a path may lose at most this fraction of its RMSE to quantization unless --force
MAX_DEGRADATION = 0.03


def _frames(data: str, input_size: tuple[int, int], count: int, split: str) -> list[dict]:
    """Calibration frames spread over the training split (not its first scenes only); evaluation frames
    are the validation split's first ``count``, those a study measures its networks on."""
    ds = open_dataset(data, split, input_size, train_augment=False)
    if len(ds) == 0:
        raise UserError(f"--data {data}: its {split} split has no frames to quantize with")
    step = max(len(ds) // count, 1) if split == "train" else 1
    return [ds[i] for i in range(0, len(ds), step)[:count]]


def stage_inputs(model_dir: Path, frames: list[dict]) -> list[list[dict[str, np.ndarray]]]:
    """For each stage graph of an exported model, the inputs it receives on each frame."""
    # the graphs' own inputs; one set of sessions: nothing here is timed
    runner = AnytimeRunner(model_dir, warmup=False, handoff=False, arenas="shared")
    per_stage: list[list[dict[str, np.ndarray]]] = [[] for _ in runner.sessions]
    for f in frames:
        img, scan = runner.check(f["image"].numpy(), f["scan"].numpy())
        env = {"image": img, "scan": scan}
        for k, (_, sess, ins, outs) in enumerate(runner.sessions):
            per_stage[k].append({n: env[n] for n in ins})
            env.update(zip(outs, sess.run(outs, {n: env[n] for n in ins})))
    return per_stage


def compare_speed(model_dir: Path, manifest: Manifest, configs: list[dict[int, str]], frame: dict,
                  reps: int = 5) -> list[tuple[float, dict[int, float]]]:
    """For each of ``configs`` (stage index -> its int8 graph in ``model_dir``; the others fp32), the
    staged runtime's median ms on ``frame`` over its stage graphs, and each stage's own median ms within
    it. Timed in the chain, not graph by graph: int8 neighbours hand each other uint8 tensors
    (``explorer.probe.rewrites.hand_off_quantized``), so a stage's precision changes what its neighbours pay
    too. The runners take turns, ``reps`` blocks of 5 timed runs each (``explorer.probe.time_chain``).
    Leaves the manifest as it was."""
    kept = (model_dir / MANIFEST).read_text()
    runners = []
    try:
        for chosen in configs:
            write_manifest(model_dir, _with_files(manifest, chosen))
            runners.append(AnytimeRunner(model_dir, arenas="shared"))
    finally:
        (model_dir / MANIFEST).write_text(kept)
    image, scan = runners[0].check(frame["image"].numpy(), frame["scan"].numpy())
    chains = [chain_runs([sess for _, sess, _, _ in r.sessions], {"image": image, "scan": scan}) for r in runners]
    blocks: list[list[list[float]]] = [[] for _ in runners]   # per runner, per block: each stage's median ms
    for _ in range(reps):
        for (runs, new_round), per_block in zip(chains, blocks):
            # one untimed round first: the other runner's buffers were in the caches
            per_block.append(time_chain(runs, 1, 5, new_round=new_round))
    return [(statistics.median(map(sum, per_block)), {k: statistics.median(t) for k, t in enumerate(zip(*per_block))})
            for per_block in blocks]


def _with_files(manifest: Manifest, chosen: dict[int, str]) -> Manifest:
    """``manifest`` running the graphs ``chosen`` (stage index -> its file) in place of those it lists."""
    return manifest.model_copy(update={"stages": [st.model_copy(update={"file": chosen.get(k, st.file)})
                                                  for k, st in enumerate(manifest.stages)]})


def path_metrics(model_dir: Path, frames: list[dict]) -> list[dict[str, float]]:
    """Per-path metrics of the export in ``model_dir`` as its graphs stand now (fp32 or int8)."""
    return runtime.path_metrics(runtime.AnytimeRunner(model_dir, warmup=False, arenas="shared"), frames)


def quantize_export(model_dir: Path, data: str, calibration_frames: int = 32, eval_frames: int = 64,
                    max_degradation: float = MAX_DEGRADATION, force: bool = False,
                    progress: Callable[[str], None] | None = None,
                    stages: "str | tuple[str, ...]" = "faster") -> Manifest:
    """Turns the fp32 export in ``model_dir`` (a scratch folder) into an int8 one in place and returns
    its manifest with what an int8 export records: which stage graphs are int8 and why (``stages="faster"``: those whose int8
    saved the staged runtime at least ``1 - INT8_KEEP_RATIO`` of their fp32 time here; ``"all"``: every
    one; a tuple: those named, as
    ``CandidateCost.int8_graphs`` names the ones a device profile prices int8), per-path metrics before and after
    on ``eval_frames`` validation frames, each path's RMSE degradation, the calibration. Refuses
    (UserError) when a path degrades by more than ``max_degradation`` unless ``force``; with
    ``"faster"``, only once keeping graphs fp32 one by one (``kept_fp32_for_accuracy``) has not brought
    every path within it while one graph is still int8."""
    _check_quantize_args(calibration_frames, eval_frames, max_degradation, stages)
    manifest = read_manifest(model_dir)
    size = tuple(manifest.input_size)
    say = progress or (lambda _: None)
    say(f"calibrating on {calibration_frames} training frames of {data}")
    frames = _frames(data, size, calibration_frames, "train")
    calib = stage_inputs(model_dir, frames)
    evaluation = _frames(data, size, eval_frames, "val")
    require_scores(evaluation, data, "rmse")   # int8 is kept where each path's RMSE holds
    say(f"measuring the fp32 paths on {len(evaluation)} validation frames")
    before = path_metrics(model_dir, evaluation)
    made = _quantize_stages(model_dir, manifest, calib, stages, say)
    share_edge_scales(list(made.values()))
    int8_files = {k: dst.name for k, dst in made.items()}
    if stages == "faster" and made:
        _drop_slower_stages(model_dir, manifest, int8_files, frames[0], say)
    trial = _Trial(model_dir, manifest, evaluation, before)
    say(f"measuring the int8 paths on {len(evaluation)} validation frames")
    after, degradation = trial.measure(int8_files)
    kept_for_accuracy = []
    if stages == "faster" and not force:
        after, degradation, kept_for_accuracy = _keep_fp32_for_accuracy(
            trial, int8_files, after, degradation, max_degradation, say)
    worst = int(np.argmax(degradation))
    if degradation[worst] > max_degradation and not force:
        last = manifest.stages[next(iter(int8_files))].name if kept_for_accuracy else None
        alone = f" even with only {last} int8" if last else ""
        raise UserError(f"int8 degrades path {worst}'s RMSE by {degradation[worst]:.1%}{alone} (> --max-degradation "
                        f"{max_degradation:.0%}; {before[worst]['rmse']:.4f} -> {after[worst]['rmse']:.4f} m): "
                        "not exported; keep fp32, calibrate on more frames, or add --force")
    quantized = _swap_in_int8(model_dir, manifest, int8_files)
    manifest.precision = "int8"
    manifest.path_metrics_fp32, manifest.path_metrics_int8 = before, after
    manifest.quantization = QuantizationRecord(
        method="onnxruntime static QDQ, each stage graph quantized whole (every operator the quantizer handles): "
               "int8 weights per channel (7-bit range), uint8 activations (ranges at the 99.999th percentile of the "
               "calibration frames)",
        int8_stages=_why(stages),
        calibration=Frames(data=data, split="train", frames=len(calib[0]) if calib else 0),
        evaluation=Frames(data=data, split="val", frames=len(evaluation)),
        rmse_degradation=degradation, max_degradation=max_degradation,
        forced=bool(force and degradation[worst] > max_degradation),
        quantized_graphs=quantized, kept_fp32_for_accuracy=kept_for_accuracy)
    return manifest


def _check_quantize_args(calibration_frames: int, eval_frames: int, max_degradation: float,
                         stages: "str | tuple[str, ...]") -> None:
    """Refuses (UserError) the options before anything is calibrated or measured."""
    if calibration_frames < 1 or eval_frames < 1:
        raise UserError("--calibration-frames and --eval-frames must be at least 1")
    if not 0 <= max_degradation:
        raise UserError(f"--max-degradation must be 0 or more, got {max_degradation}")
    if isinstance(stages, str) and stages not in INT8_STAGES:
        raise UserError(f"--int8-stages {stages}: use {' or '.join(INT8_STAGES)}")


def _quantize_stages(model_dir: Path, manifest: Manifest, calib: list[list[dict[str, np.ndarray]]],
                     stages: "str | tuple[str, ...]", say: Callable[[str], None]) -> dict[int, Path]:
    """Quantizes each stage graph that ``stages`` lets be int8 next to its fp32 one; returns stage
    index -> its int8 graph, for those the quantizer could quantize. Marks every stage fp32 for now."""
    made: dict[int, Path] = {}
    for k, stage in enumerate(manifest.stages):
        src = model_dir / stage.file
        dst = src.with_name(src.stem + ".int8.onnx")
        stage.precision = "fp32"
        if stage.is_scan_path:
            continue   # the scan's own map: nothing to quantize
        if not isinstance(stages, str) and stage.name not in stages:
            continue
        say(f"quantizing {stage.file}")
        if quantize_graph(src, dst, calib[k]):
            made[k] = dst
        else:
            dst.unlink(missing_ok=True)
    return made


def _drop_slower_stages(model_dir: Path, manifest: Manifest, int8_files: dict[int, str], frame: dict,
                        say: Callable[[str], None]) -> None:
    """From every quantized stage int8, each in turn goes back to fp32 (out of ``int8_files``, its
    int8 graph deleted) unless int8 saves the staged runtime at least 1 - INT8_KEEP_RATIO of that
    stage's fp32 time; each stage records what it measured (``ms_here``)."""
    say("timing the staged runtime with each quantized stage int8 and fp32")
    for k in list(int8_files):
        stage = manifest.stages[k]
        (with_ms, with_stages), (without_ms, without_stages) = compare_speed(
            model_dir, manifest, [int8_files, {j: f for j, f in int8_files.items() if j != k}], frame)
        fp32_ms, int8_ms = without_stages[k], with_stages[k]
        keep = with_ms <= without_ms - (1 - INT8_KEEP_RATIO) * fp32_ms
        stage.ms_here = StageTiming(fp32=round(fp32_ms, 4), int8=round(int8_ms, 4),
                                    staged_fp32=round(without_ms, 4), staged_int8=round(with_ms, 4))
        say(f"  {stage.name}: staged runtime {with_ms:.2f} ms with it int8, {without_ms:.2f} ms with it fp32 "
            "on this machine: " + ("int8" if keep else "kept fp32"))
        if not keep:
            (model_dir / int8_files.pop(k)).unlink()


class _Trial:
    """Measures the export with a chosen set of stage graphs int8: writes the manifest that runs
    them, marks each stage's precision, and compares every path with its fp32 metrics."""

    def __init__(self, model_dir: Path, manifest: Manifest, evaluation: list[dict],
                 before: PathMetrics) -> None:
        self.model_dir, self.manifest, self.evaluation, self.before = model_dir, manifest, evaluation, before

    def choose(self, chosen: dict[int, str]) -> None:
        for k, stage in enumerate(self.manifest.stages):
            stage.precision = "int8" if k in chosen else "fp32"

    def measure(self, chosen: dict[int, str]) -> tuple[list[dict[str, float]], list[float]]:
        """Per-path metrics and RMSE degradation with exactly the graphs ``chosen`` int8."""
        self.choose(chosen)
        write_manifest(self.model_dir, _with_files(self.manifest, chosen))
        after = path_metrics(self.model_dir, self.evaluation)
        return after, [a["rmse"] / b["rmse"] - 1 if b["rmse"] > 0 else 0.0 for a, b in zip(after, self.before)]


def _keep_fp32_for_accuracy(trial: _Trial, int8_files: dict[int, str], after: list[dict[str, float]],
                            degradation: list[float], max_degradation: float, say: Callable[[str], None],
                            ) -> tuple[list[dict[str, float]], list[float], list[str]]:
    """Over the limit: gives back, one at a time, the int8 graph whose fp32 return helps the worst
    path most (then the one that saved least time), while more than one int8 graph is left. Returns
    the metrics and degradation as they end, and the stages given back."""
    kept_for_accuracy = []
    stages = trial.manifest.stages
    while len(int8_files) > 1 and max(degradation) > max_degradation:
        trials = []
        for k in int8_files:
            a, d = trial.measure({j: f for j, f in int8_files.items() if j != k})
            saved = stages[k].ms_here
            trials.append((max(d), saved.fp32 - saved.int8 if saved else 0.0, k, a, d))
        worst_after, _, k, after, degradation = min(trials, key=lambda t: t[:2])
        name = stages[k].name
        say(f"  {name} kept fp32: with it int8 a path lost more than {max_degradation:.1%} RMSE "
            f"(worst path without it {worst_after:+.1%})")
        kept_for_accuracy.append(name)
        (trial.model_dir / int8_files.pop(k)).unlink()
    trial.choose(int8_files)
    return after, degradation, kept_for_accuracy


def _swap_in_int8(model_dir: Path, manifest: Manifest, int8_files: dict[int, str]) -> list[str]:
    """Puts each int8 graph in its stage's place (deleting the fp32 one) and writes the manifest that
    runs them; returns the fp32 files replaced."""
    quantized = []
    for k, stage in enumerate(manifest.stages):
        if k in int8_files:
            (model_dir / stage.file).unlink()
            quantized.append(stage.file)
            stage.file = int8_files[k]
    write_manifest(model_dir, manifest)
    return quantized


def _why(stages: "str | tuple[str, ...]") -> str:
    if stages == "all":
        return "all"
    if stages == "faster":
        return (f"faster: int8 where it saved the staged runtime at least {1 - INT8_KEEP_RATIO:.0%} of that stage "
                "graph's fp32 time on the exporting machine (ms_here), and every path stayed within max_degradation")
    return "as searched: those the device profile prices faster in int8"


