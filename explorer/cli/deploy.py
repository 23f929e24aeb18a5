"""``explorer export``, ``run`` and ``curve``: a trained candidate as ONNX stages, run under deadlines."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from explorer.errors import UserError
from explorer.cli._common import (MAX_THREADS, _add_provider, _bounded_int, _ms, _size, ascii_digits, deprecated_alias,
                                  runtime_install)

if TYPE_CHECKING:
    from explorer.deploy.manifest import Manifest


@ascii_digits
def _percent(text: str) -> float:
    try:
        value = float(text.strip().rstrip("%"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a percentage (e.g. 3 or 3%)") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"'{text}': must be 0 or more")
    return value


def cmd_export(args) -> None:
    from explorer.console import console, err_console, progress
    from explorer.files import check_writable_folder
    from explorer.deploy.export import Measurement, Quantization, export_from_checkpoint
    from explorer.study.export import AS_SEARCHED, export_from_study
    if bool(args.study) == bool(args.checkpoint):
        raise UserError("give either --study S (optionally --trial N) or --checkpoint FILE")
    if args.checkpoint and args.trial is not None:
        raise UserError("--trial picks a trial of --study; a --checkpoint is one network already")
    if args.quantize not in (None, "none", "int8"):
        raise UserError(f"--quantize {args.quantize}: use int8 or none")
    if args.eval_frames is not None and args.eval_frames < 1:
        raise UserError("--eval-frames must be at least 1")
    # a study's own data and frames unless told; a checkpoint's: the data it was trained on
    data = args.data
    if data is None and args.quantize == "int8":
        err_console.print(f"no --data: calibrating and measuring on the {'study' if args.study else 'checkpoint'}'s "
                          "data")
    quant = None
    if args.quantize == "int8":
        quant = Quantization(data=data, calibration_frames=args.calibration_frames,
                             eval_frames=args.eval_frames or 96, max_degradation=args.max_degradation / 100,
                             force=args.force, stages=args.int8_stages or "faster")
    elif args.force or args.int8_stages:
        raise UserError("--force and --int8-stages are read by --quantize int8 only")
    elif args.quantize is None and args.study:
        quant = AS_SEARCHED
    # the export is built beside --out, then swapped in: a folder it cannot write is one line before any work
    check_writable_folder(Path(args.out).resolve().parent, "export", "give --out a folder you can write", keep=False)
    curve = Path(args.out) / "anytime_curve.json"   # measured on the graphs the export replaces
    had_curve = curve.is_file()
    # what the export is doing shows on one status line that a refusal clears: its error is then the
    # one line on stderr
    with progress(transient=True) as bar:
        task = bar.add_task("export", total=None, status="")
        say = lambda msg: bar.update(task, status=str(msg))  # noqa: E731
        if args.study:
            manifest = export_from_study(args.study, args.trial, Path(args.out), args.storage,
                                         Path(args.reports), args.input_size, args.device, quant, say,
                                         data=data, eval_frames=args.eval_frames)
        else:
            manifest = export_from_checkpoint(Path(args.checkpoint), Path(args.out), args.input_size, args.device,
                                              quant, say, Measurement(data, args.eval_frames or 96))
    _print_measured(manifest)
    console.print(f"exported {len(manifest.stages)} stage graphs to {args.out} (max |onnx - torch| "
                  f"{manifest.verification.max_abs_diff:.2e}{' before quantization' if manifest.quantization else ''})"
                  + (f", and {manifest.curve_frames.frames} validation frames that `explorer curve` measures on"
                     if manifest.curve_frames else ""), markup=False, highlight=False)
    _print_dropped(manifest)
    if had_curve and not curve.exists():
        console.print(f"removed {curve}: it measured the graphs this export replaced; `explorer curve {args.out}` "
                      "measures these", markup=False, highlight=False)
    if manifest.quantization:
        _print_int8(manifest)


def _print_dropped(manifest: Manifest) -> None:
    """The exits the export's own measurement left out of what ships (beyond the study's)."""
    from explorer.console import console
    from explorer.model.shipped import DroppedExit
    first = manifest.path_metrics[0] if manifest.path_metrics else {}
    metric = "rmse" if "rmse" in first else next(iter(first), "error")
    for drop in manifest.source.dropped_exits or []:
        exit_ = DroppedExit.from_dict(drop)
        if exit_.measured_on:
            console.print(f"{exit_.describe(metric)}: left out of what ships (--keep-every-exit on the search "
                          "keeps every exit)", markup=False, highlight=False)


def _print_int8(manifest: Manifest) -> None:
    """What quantizing an export did: each path's RMSE before and after, the graphs made int8, and why
    some were not."""
    import pandas as pd
    from explorer.console import console, print_frame
    q = manifest.quantization
    frame = pd.DataFrame({"path": range(len(q.rmse_degradation)),
                          "fp32 rmse": [m["rmse"] for m in manifest.path_metrics_fp32 or []],
                          "int8 rmse": [m["rmse"] for m in manifest.path_metrics_int8 or []],
                          "change %": [100 * d for d in q.rmse_degradation]})
    print_frame(frame, f"int8 vs fp32 on {q.evaluation.frames} validation frames of {q.evaluation.data}"
                + (" (--force: over --max-degradation)" if q.forced else ""))
    int8 = [st.name for st in manifest.stages if st.precision == "int8"]
    console.print(f"int8 stage graphs: {len(int8)} of {len(manifest.stages)}"
                  + (f" ({', '.join(int8)})" if int8 else " (none ran at least 5% faster in int8 here: the "
                     "export is fp32; --int8-stages all forces int8)"))
    if manifest.expected_cost_note:
        console.print(f"the manifest's expected costs per device are {manifest.expected_cost_note}",
                      markup=False, highlight=False)
    if q.kept_fp32_for_accuracy:
        console.print(f"kept fp32 because int8 took a path past --max-degradation: "
                      f"{', '.join(q.kept_fp32_for_accuracy)}")


def _print_measured(manifest: Manifest) -> None:
    """The export's own figures, where they come from, and a line when it is deployed at a size its
    weights were not trained or tuned at."""
    import math

    import pandas as pd
    from explorer.console import console, print_frame
    measured = manifest.measured
    if not measured:
        return
    size = "x".join(map(str, manifest.input_size))
    columns = {"rmse": "rmse (m)", "delta1": "delta1", "photometric": "photometric"}
    metrics = manifest.path_metrics
    frame = pd.DataFrame({"path": range(len(metrics))})
    for key, title in columns.items():   # what the frames could measure: depth, the camera's motion, or both
        values = [m.get(key) for m in metrics]
        if any(v is not None and math.isfinite(v) for v in values):
            frame[title] = values
    print_frame(frame, f"measured on the exported graphs at {size}, {measured.frames} validation frames of "
                f"{measured.data}")
    tuned = manifest.tuned_size
    if tuned and tuple(tuned) != tuple(manifest.input_size):
        console.print(f"exported at {size}, but its weights were trained at {'x'.join(map(str, tuned))}: the manifest "
                      f"holds what they do at {size} (above), not the study's figures", markup=False, highlight=False)


def cmd_run(args) -> None:
    from explorer.console import console, print_json
    from explorer.deploy.runtime import run_files
    res = run_files(Path(args.model), Path(args.image), Path(args.scan), args.deadline,
                    Path(args.out) if args.out else None, args.threads, args.provider,
                    lidar=Path(args.lidar_yaml) if args.lidar_yaml else None,
                    intrinsics=Path(args.intrinsics) if args.intrinsics else None)
    if args.json:
        print_json(res)
        return
    console.print(f"returned path {res['path']} (ready at {res['ready_ms']:.2f} ms, deadline {args.deadline:g} ms); "
                  f"{res['completed_paths']} path(s) completed" + (f"; wrote {args.out}" if args.out else ""))
    later = [p for p, _ in res["timeline"] if p > res["path"]]
    if later:
        console.print(f"path(s) {', '.join(map(str, later))} ready too but less accurate than path {res['path']} as "
                      "the export measured them: not returned", markup=False, highlight=False)
    if "scan_rows" in res:
        low, high = res["scan_rows"]
        console.print(f"scan: {res['scan_columns']} column(s) with a return, on input rows {low}-{high} (median "
                      f"{res['projected_row']}; the model's scan row {res['scan_row']})", markup=False, highlight=False)


def _curve_profile(args) -> tuple[str | None, dict | None]:
    """``explorer curve``'s profile of this machine: --device; else the one an earlier curve kept for this
    machine (unless --recalibrate); else none yet, and the options to calibrate it with (the profile is
    then kept)."""
    from explorer.calibration.kept import find_kept
    from explorer.cli.devices import QUICK_PROBE
    from explorer.console import err_console
    if args.device is not None:
        if args.recalibrate:
            raise UserError("--recalibrate measures this machine again: give it without --device")
        return args.device, None
    found = None if args.recalibrate else find_kept(args.provider, args.quick)
    if found:
        err_console.print(f"no --device: this machine's profile, kept by an earlier `explorer curve`: {found} "
                          "(--recalibrate measures it again)", markup=False, highlight=False)
        return str(found), None
    err_console.print("no --device: this machine is calibrated first, "
                      + ("quickly (a third of the sweep)" if args.quick else
                         "which takes several minutes (--quick: a third of the sweep)")
                      + ", and the profile kept for the next `explorer curve` here; `explorer calibrate --out "
                      "mybox.yaml` once, then --device mybox.yaml, skips it", markup=False, highlight=False)
    return None, {"scale": 0.35, **QUICK_PROBE} if args.quick else {"scale": 0.5}


def _keeper(args, kept: list):
    """Keeps a profile just calibrated for the next ``explorer curve``; a place that cannot be written
    loses it, with a line, and the curve goes on."""
    from explorer.calibration.kept import keep_profile
    from explorer.console import err_console

    def keep(profile) -> None:
        try:
            kept.append(keep_profile(profile, args.provider, args.quick))
        except OSError as exc:
            err_console.print(f"could not keep this machine's profile ({exc.strerror or exc}): the next "
                              "`explorer curve` calibrates again", markup=False, highlight=False)
    return keep


def cmd_curve(args) -> None:
    from explorer.console import console, print_json
    from explorer.files import check_writable_folder
    curve = Path(args.model) / "anytime_curve.json"   # written after the measurement: checked before it
    if curve.is_dir():
        raise UserError(f"{curve}: is a folder; move it away so that explorer curve can write the curve there")
    if Path(args.model).is_dir():
        check_writable_folder(args.model, "anytime curve", "copy the export to a folder you can write")
    if runtime_install():   # no torch: the export's own frames and the manifest's prediction only
        res = _device_curve(args)
    else:
        res = _full_curve(args)
    if args.json:
        print_json(res)
        return
    m, p = res["measured_anytime_loss"], res["predicted_anytime_loss"]
    size = "x".join(map(str, res["input_size"]))
    by = f"{res['device']}" + (" (the export's expected costs)" if res.get("predicted_from") == "manifest" else "")
    console.print(f"anytime loss U(0, {res['b_max_ms']:.1f} ms) on this machine: measured {m:.4f}, predicted by "
                  f"{by} {p:.4f} ({m / p - 1:+.1%}); on {res['frames']} validation frames of {res['data']} "
                  f"at {size}; written to {Path(args.model) / 'anytime_curve.json'}")
    if res["precision"] != res["priced_precision"]:
        console.print(f"(the model is {res['precision']}; the profile prices {res['priced_precision']} layers only, "
                      f"so the prediction is an {res['priced_precision']} one)")


def _say(line: str) -> None:
    from explorer.console import err_console
    err_console.print(line, markup=False, highlight=False)


def _device_curve(args) -> dict:
    """``explorer curve`` in the runtime install: the export's frames, the manifest's prediction."""
    from explorer.console import progress
    from explorer.deploy.curve import device_curve
    with progress(transient=True) as bar:
        task = bar.add_task("deadlines", total=args.deadlines, status="")
        return device_curve(Path(args.model), args.device, args.frames, args.deadlines,
                            progress=lambda i, n: bar.update(task, completed=i), provider=args.provider, say=_say)


def _full_curve(args) -> dict:
    """``explorer curve`` with the whole package: any data, any profile, or this machine calibrated."""
    from explorer.calibration.curve import curve_check
    from explorer.console import Phases, progress
    kept: list[Path] = []
    device, calibration = _curve_profile(args)
    with progress(transient=True) as bar:
        task = bar.add_task("deadlines", total=args.deadlines, status="")
        res = curve_check(Path(args.model), args.data, device, args.frames, args.deadlines,
                          progress=lambda i, n: bar.update(task, completed=i), provider=args.provider,
                          calibration=calibration,
                          calibration_progress=Phases(bar, "calibrating this machine: ") if calibration else None,
                          keep=_keeper(args, kept) if calibration else None, say=_say)
    if kept:
        _say(f"kept this machine's profile at {kept[0]}: the next `explorer curve` here reuses it, and "
             f"--device {kept[0]} prices with it (explorer rescore, search)")
    return res


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    s = add("export", cmd_export, "export a trained candidate as ONNX stage graphs + manifest")
    s.add_argument("--study")
    s.add_argument("--trial", type=int, help="trial number (default: the best)")
    s.add_argument("--checkpoint", help="export a checkpoint instead of a study trial")
    s.add_argument("--storage")
    s.add_argument("--out", required=True, help="folder to write the stage graphs and manifest.json into "
                   "(explorer run and explorer curve read it)")
    s.add_argument("--input-size", type=_size, default=None,
                   help="deployment resolution HxW (default: the study's --input-size; a checkpoint's training size)")
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--device", action="append", help="devices whose expected costs go in the manifest")
    s.add_argument("--quantize", default=None, metavar="int8|none",
                   help="int8: static quantization (onnxruntime QDQ) calibrated on --data; every path's metrics "
                   "are measured again and written beside the fp32 ones (default: as the trial was searched, "
                   "int8 for a candidate of precision int8, else none)")
    s.add_argument("--data", help="frames every exported path is measured on (val split) and int8 is "
                   "calibrated on (train split) (default: the study's data; for a checkpoint, the data it was trained "
                   "on)")
    s.add_argument("--calibration-frames", type=int, default=32, help="frames to calibrate on (default 32)")
    s.add_argument("--eval-frames", type=int, default=None, help="validation frames (the split's first) every "
                   "path is measured on (default: those of the study's figures, 96)")
    s.add_argument("--max-degradation", type=_percent, default=3.0, metavar="PCT",
                   help="refuse int8 if a path's RMSE grows by more than this (default 3%%)")
    s.add_argument("--force", action="store_true", help="export int8 even past --max-degradation")
    s.add_argument("--int8-stages", choices=("faster", "all"), default=None,
                   help="faster (default): each stage graph is int8 only where that makes the staged runtime "
                   "faster by at least 5%% of the graph's fp32 time on this machine (timed at export, int8 "
                   "neighbours handing each other uint8 tensors), and graphs that take a path past "
                   "--max-degradation go back to fp32 one by one; all: every stage int8 (for a target other "
                   "than this machine)")
    s.add_argument("--reports", **reports)

    s = add("run", cmd_run, "run an exported model under a deadline and return the best depth map")
    s.add_argument("model", help="folder written by explorer export")
    s.add_argument("--image", required=True)
    s.add_argument("--scan", required=True, help=".csv or .npy: one depth (m) per image column, 0 = none; with "
                   "--lidar: one range (m) per beam of the LiDAR, inf/nan/0 = no return")
    # dest: not ``lidar``, which names the training commands' --lidar (the scans of --data: resolve_data)
    s.add_argument("--lidar", dest="lidar_yaml", metavar="LIDAR.YAML",
                   help="the LiDAR and its mount (fov, resolution, range_min, range_max, height, tilt, ... or "
                   "T_cam_lidar): --scan is then its ranges, projected into the image, and --image may be any "
                   "size (resized to the model's, bilinear); needs --intrinsics")
    s.add_argument("--intrinsics", metavar="FILE", help="with --lidar: the camera matrix of --image at its own "
                   "size, as fx fy cx cy or the 9 entries of K (pixels)")
    s.add_argument("--deadline", type=_ms, required=True, help="e.g. 8ms")
    s.add_argument("--out", help="depth map file to write: .png (16-bit, millimetres) or .npy (metres) "
                   "(default: none written)")
    s.add_argument("--threads", type=_bounded_int(1, MAX_THREADS, "threads"), default=None)
    _add_provider(s)
    s.add_argument("--json", action="store_true")

    s = add("curve", cmd_curve, "measure an exported model's anytime curve here and compare with the prediction")
    s.add_argument("model", help="folder written by explorer export")
    s.add_argument("--data", default=None, help="frames to measure on (validation split; needs the full package) "
                   "(default: the validation frames the export carries, else synthetic)")
    s.add_argument("--device", help="a device the export's manifest prices (its expected costs predict the curve; "
                   "what the runtime install needs), or a host profile from explorer calibrate (default: the "
                   "profile of this machine an earlier explorer curve kept, else calibrate this machine now, several "
                   "minutes, and keep it)")
    s.add_argument("--quick", action="store_true", help="without --device: calibrate quickly (a third of the "
                   "sweep); a kept full calibration serves too")
    s.add_argument("--recalibrate", action="store_true", help="calibrate this machine again even where a profile "
                   "of it is kept (and keep the new one)")
    s.add_argument("--frames", type=_bounded_int(1, 10_000, "validation frames"), default=16, help="validation frames, each run at every deadline "
                   "(default 16)")
    s.add_argument("--deadlines", type=_bounded_int(2, 10_000, "deadlines, each run on every frame"), default=40)
    _add_provider(s)
    s.add_argument("--json", action="store_true")
