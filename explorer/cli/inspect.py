"""``explorer space``, ``profile``, ``anytime``, ``enumerate``, ``data``: look at spaces, candidates,
costs and data without training anything."""

from __future__ import annotations

from pathlib import Path

from explorer.errors import UserError
from explorer.cli._common import MAX_THREADS, _Parser, _add_provider, _bounded_int, _check_provider, _size, deprecated_alias


def cmd_space_show(args) -> None:
    from explorer.console import console, print_json
    from explorer.space import SearchSpace
    space = SearchSpace.from_yaml(args.space)
    dims = space.dimensions()
    if args.json:
        print_json({"name": space.name, "size": space.size, "source": space.source,
                    "dimensions": {k: list(v) for k, v in dims.items()},
                    "required_exits": list(space.required_exits)})
        return
    console.print(f"[bold]{space.name}[/bold]  ({space.source})  {space.description}")
    console.print(f"candidates: [bold]{space.size:,}[/bold]")
    for k, v in dims.items():
        console.print(f"  {k:18s} {list(v)}")
    if space.required_exits:
        console.print(f"  {'required exits':18s} {list(space.required_exits)}")


def _candidates_of(path: str) -> list:
    """A candidate file, or every candidate of a (small) space."""
    from explorer.space import Candidate, SearchSpace, resolve_space_path, load_yaml
    p = resolve_space_path(path) if not Path(path).is_file() else Path(path)
    data = load_yaml(p)
    if isinstance(data, dict) and "candidate" in data:
        return [Candidate.from_dict(data["candidate"], str(p))]
    space = SearchSpace.from_yaml(p)
    if space.size > 16:
        raise UserError(f"{p} has {space.size:,} candidates: profile takes a candidate file or a space of "
                        "at most 16 (use `explorer enumerate` for whole spaces)")
    return list(space.enumerate())


def _profile_reference(args, device) -> None:
    from explorer.console import console, print_frame, print_json
    from explorer.cost import profile_reference
    from explorer.model.reference import get_reference
    ref = get_reference(args.target)
    if args.measure:
        raise UserError("--measure works on candidates only; reference networks are costed, not measured")
    frame = profile_reference(ref.name, args.input_size, device)
    if args.json:
        published = ref.paper.__dict__ if ref.paper else None
        print_json({"reference": ref.name, "description": ref.description, "input_size": list(args.input_size),
                    "paths": frame.to_dict("records"), "published": published})
        return
    console.print(f"[bold]{ref.name}[/bold]  {ref.description}")
    print_frame(frame, f"at {args.input_size[0]}x{args.input_size[1]}" + (f" on {device.name}" if device else ""))


def cmd_profile(args) -> None:
    from explorer.console import console, print_frame, print_json
    from explorer.cost import get_device, profile_candidate
    from explorer.space import SPACES_DIR
    out = []
    device = get_device(args.device) if args.device is not None else None
    looks_like_file = args.target.endswith((".yaml", ".yml")) or "/" in args.target
    if not looks_like_file and not Path(args.target).is_file() and not (SPACES_DIR / f"{args.target}.yaml").is_file():
        return _profile_reference(args, device)   # a reference network, or one line naming them
    if args.measure:
        _check_provider(args.provider)
    for cand in _candidates_of(args.target):
        frame = profile_candidate(cand, args.input_size, device)
        entry = {"candidate": cand.to_dict(), "key": cand.key, "input_size": list(args.input_size),
                 "paths": frame.to_dict("records")}
        if args.measure:
            from explorer.calibration.measure import measure_candidate
            m = measure_candidate(cand, args.input_size, threads=args.threads, repeats=args.repeats,
                                  provider=args.provider)
            frame["measured_ms"] = m.path_ms
            frame.loc[0, "measured_ms"] = 0.0
            entry["paths"] = frame.to_dict("records")
            entry["measured"] = {"stage_ms": m.stage_ms, "whole_graph_ms": m.whole_ms,
                                 "staged_total_ms": m.staged_total_ms, "staging_overhead": m.staging_overhead,
                                 "path0_ms": m.path_ms[0], "conditions": m.conditions}
        out.append(entry)
        if not args.json:
            console.print(f"[bold]{cand.key}[/bold]  {cand.describe()}")
            title = f"per path at {args.input_size[0]}x{args.input_size[1]}" + (f" on {device.name}" if device else "")
            print_frame(frame, title)
            if args.measure:
                console.print(f"whole graph {m.whole_ms:.3f} ms, sum of stages {m.staged_total_ms:.3f} ms "
                              f"({m.staging_overhead:+.1%}); onnxruntime {m.conditions['onnxruntime']}, "
                              f"{m.conditions['threads']} threads, median of {m.conditions['repeats']}")
    if args.json:
        print_json(out[0] if len(out) == 1 else out)


def cmd_anytime(args) -> None:
    from explorer.console import console, print_json
    from explorer.anytime import anytime_loss, check_losses, interval_probabilities, parse_budget
    if not args.path:
        raise UserError("give at least one --path COST:LOSS (path 0 is added with cost 0 if missing)")
    pairs = []
    for text in args.path:
        try:
            cost, loss = text.split(":")
            pairs.append((float(cost), float(loss)))
        except ValueError:
            raise UserError(f"--path {text!r} is not COST:LOSS (e.g. 6.4:0.465)") from None
    pairs.sort()
    costs, losses = [p[0] for p in pairs], [p[1] for p in pairs]
    check_losses(losses)
    dist = parse_budget(args.budget)
    value = anytime_loss(costs, losses, dist)
    weights = interval_probabilities(costs, dist)
    if args.json:
        print_json({"budget": dist.spec, "anytime_loss": value, "costs": costs, "losses": losses,
                    "weights": list(weights)})
        return
    console.print(f"anytime loss for {dist.spec}: [bold]{value:.4f}[/bold]")
    for cost, loss, w in zip(costs, losses, weights):
        console.print(f"  path at {cost:g} {dist.unit}: loss {loss:g}, P(output) = {w:.4f}")


def cmd_enumerate(args) -> None:
    from explorer.console import console, print_frame, progress
    from explorer.cost.enumerate import front_columns, write_enumeration
    from explorer.files import check_writable_folder
    from explorer.space import SearchSpace, check_size
    space = SearchSpace.from_yaml(args.space)
    check_size(args.input_size, space.max_stride, "--input-size")
    front = front_columns(args.front)
    for flag, path in (("--csv", args.csv), ("--parquet", args.parquet)):
        if path:
            check_writable_folder(Path(path).parent, "table", f"give {flag} a path you can write", keep=False)
    with progress(transient=True) as bar:
        task = bar.add_task(f"costing {space.name}", total=space.size, status="")
        done = write_enumeration(space, args.device, args.budget, args.input_size, csv=args.csv, parquet=args.parquet,
                                 front=front, progress=lambda i, n: bar.update(task, completed=i))
    for path in (args.csv, args.parquet):
        if path:
            console.print(f"wrote {done.size:,} candidates to {path}")
    console.print(f"{done.size:,} candidates costed in {done.seconds:.1f} s ({done.size / done.seconds:,.0f}/s)")
    cols = ["key", "params", "macs", "paths", "first_exit_ms", "last_exit_ms", "p_path0"]
    cols += [c for c in front if c not in cols]
    shown = done.front.head(args.top)
    more = f", the first {len(shown)} shown (--top)" if len(shown) < len(done.front) else ""
    print_frame(shown[cols], f"Pareto front of {', '.join(front)} over every candidate: "
                             f"{len(done.front):,} candidates{more}")


def cmd_data_inspect(args) -> None:
    import numpy as np
    from explorer.console import console, print_json, progress
    from explorer.data import open_dataset
    from explorer.metrics import MetricAverager, depth_metrics
    from explorer.model import interpolate_scan
    if args.out:
        _check_drawing_out(Path(args.out), args.data)
    with progress(transient=True) as bar:
        task = bar.add_task("preparing the data (generated or decoded once, then cached)", total=None, status="")
        ds = open_dataset(args.data, args.split, args.input_size, train_augment=False,
                          progress=lambda i, n: bar.update(task, completed=i, total=n))
        try:
            other = open_dataset(args.data, "train" if args.split == "val" else "val", args.input_size,
                                 train_augment=False)
        except UserError as exc:   # e.g. a folder of Ma et al.'s val/ alone: this split is still worth a look
            other = str(exc)
    n = len(ds) if not args.frames else min(args.frames, len(ds))
    if n == 0:
        raise UserError(f"data {args.data}: the {args.split} split is empty")
    avg, dmin, dmax, valid, scan_valid, rows, posed = MetricAverager(), np.inf, 0.0, [], [], [], 0
    for i in range(n):
        item = ds[i]
        posed += bool(item.get("pose_known", False))
        d = item["depth"]
        pos = d[d > 0]
        if pos.numel():
            dmin, dmax = min(dmin, float(pos.min())), max(dmax, float(pos.max()))
        valid.append(float((d > 0).float().mean()))
        scan_valid.append(float((item["scan"] > 0).float().mean()))
        rows.append(item["scan_rows"].numpy())
        p0 = interpolate_scan(item["scan"][None], d.shape[1])[0]
        avg.add(depth_metrics(p0, d))
    rows = np.concatenate(rows)
    res = {"data": str(ds.name), "split": args.split, "frames": len(ds), "inspected": n,
           "input_size": list(args.input_size), "image_shape": list(item["image"].shape),
           "depth_range_m": [dmin, dmax], "valid_depth_fraction": float(np.mean(valid)),
           "scan_return_fraction": float(np.mean(scan_valid)), "scan_row": item["scan_row"],
           "scan_rows_range": [int(rows.min()), int(rows.max())], "path0": avg.result(),
           "posed_frames": posed if getattr(ds, "sequence", False) else None,
           "splits": _splits(ds, other, args.split), "source": _source_facts(ds)}
    if args.out:
        _draw_scan(ds[0], Path(args.out))
        res["png"] = str(args.out)
    if args.json:
        print_json(res)
        return
    _print_inspection(console, res, args)


def _splits(ds, other, split: str) -> dict:
    """Both splits' sizes and ends by frame name, and whether they share a frame (they must not);
    ``other``: the other split, or why it could not be opened."""
    other_split = "train" if split == "val" else "val"
    names = {split: ds.frame_names(), other_split: [] if isinstance(other, str) else other.frame_names()}
    out = {s: {"frames": len(v), "first": v[0] if v else None, "last": v[-1] if v else None}
           for s, v in names.items()}
    if isinstance(other, str):
        out[other_split]["unavailable"] = other
    out["shared_frames"] = len(set(names["train"]) & set(names["val"]))
    return out


def _source_facts(ds) -> dict:
    """What a recording's reader counted while pairing its streams (ROS bags), else nothing."""
    source = getattr(ds, "frames", None) or getattr(ds, "source", None)
    counts = getattr(source, "counts", None)
    return {"counts": dict(counts)} if counts else {}


def _print_inspection(console, res: dict, args) -> None:
    sp = res["splits"]
    console.print(f"[bold]{res['data']}[/bold] {args.split}: {res['frames']} frames (inspected {res['inspected']}) at "
                  f"{args.input_size[0]}x{args.input_size[1]}")
    for name in ("train", "val"):
        s = sp[name]
        console.print(f"  {name}: " + (f"unavailable ({s['unavailable']})" if "unavailable" in s else
                                         f"{s['frames']} frames, {s['first']} .. {s['last']}"), markup=False)
    shared = sp["shared_frames"]
    console.print("  no frame is in both splits" if not shared else
                  f"  [red]{shared} frame(s) are in both splits[/red]")
    if res["source"].get("counts"):
        console.print("  pairing: " + ", ".join(f"{k} {v}" for k, v in res["source"]["counts"].items()))
    lo, hi = res["scan_rows_range"]
    where = f"row {lo}" if lo == hi else f"rows {lo}-{hi} (median {res['scan_row']})"
    depth = (f"depth {res['depth_range_m'][0]:.2f}-{res['depth_range_m'][1]:.2f} m, "
             f"{res['valid_depth_fraction']:.1%} of pixels valid" if res["valid_depth_fraction"] > 0 else "no depth")
    console.print(f"  {depth}; scan on {where}, {res['scan_return_fraction']:.1%} of columns with a return")
    p0 = res["path0"]
    if res["valid_depth_fraction"] > 0:
        console.print(f"  path 0 (scan, nearest): RMSE {p0['rmse']:.3f} m, REL {p0['rel']:.3f}, "
                      f"delta1 {p0['delta1']:.3f}")
    else:
        console.print("  no depth: a study scores each path by its photometric error (--metric photometric)")
    if res["posed_frames"] is not None:
        console.print(f"  camera motion known for {res['posed_frames']} of {res['inspected']} inspected frames (given, "
                      "or measured by the LiDAR on validation frames; a frame without it is not scored photometrically)")
    if res.get("png"):
        console.print(f"  the first frame with its scan drawn over it: {res['png']}")


def _check_drawing_out(out: Path, data: str) -> None:
    """``--out`` refused before any frame is read where the drawing cannot go: not a PNG name, a folder,
    a folder nobody can write, or a file of the data set itself (a frame, its list, the recording), or
    any place inside a data set that is a folder (a new image there would be read as a frame)."""
    from explorer.data import parse_data_spec
    from explorer.files import check_writable_folder
    if out.suffix.lower() != ".png":
        raise UserError(f"--out {out}: the drawing is a PNG; give a name ending in .png")
    if out.is_dir():
        raise UserError(f"--out {out}: is a folder; give a file name ending in .png")
    spec = parse_data_spec(data)
    sources = [Path(x) for x in (spec.path, spec.val_option) if x and Path(x).exists()]
    target = out.resolve()
    for src in sources:
        src = src.resolve()
        if target == src or (src.is_dir() and target.is_relative_to(src)) or _listed_in(target, src):
            raise UserError(f"--out {out}: is part of the data set {data}; write the drawing outside it")
    check_writable_folder(out.parent, "drawing", "give --out a path you can write", keep=False)


def _listed_in(target: Path, listing: Path) -> bool:
    """Whether the text file ``listing`` (a CSV of image,depth pairs) names the existing file ``target``."""
    if not target.exists() or listing.suffix.lower() not in (".csv", ".txt"):
        return False
    text = listing.read_bytes()[:1 << 24].decode("utf-8", errors="replace")
    names = (field.strip() for line in text.splitlines() for field in line.split(","))
    return any(name and (listing.parent / name).resolve() == target for name in names)


def _draw_scan(item: dict, out: Path) -> None:
    """The frame with each column's return drawn at its row, coloured by depth (near red, far blue)."""
    import numpy as np
    from PIL import Image

    from explorer.files import write_atomically
    rgb = (item["image"].permute(1, 2, 0).numpy() * 255).astype(np.uint8).copy()
    scan, rows = item["scan"].numpy(), item["scan_rows"].numpy()
    h, w = rgb.shape[:2]
    cols = np.nonzero(scan > 0)[0]
    if len(cols):
        t = (scan[cols] - scan[cols].min()) / max(float(np.ptp(scan[cols])), 1e-6)
        colour = np.stack([255 * (1 - t), 64 * np.ones_like(t), 255 * t], axis=1).astype(np.uint8)
        for dy in (-1, 0, 1):
            rgb[np.clip(rows[cols] + dy, 0, h - 1), cols] = colour
    import io
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(out, buf.getvalue())


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    sp = add("space", None, "inspect a search space")
    ssub = sp.add_subparsers(dest="sub", required=True, parser_class=_Parser, metavar="SUBCOMMAND")
    s = ssub.add_parser("show", help="size, dimensions and choices of a space")
    s.add_argument("space", help="YAML file or shipped name (anytime_depth, paper, tiny)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_space_show)

    s = add("profile", cmd_profile, "per-path parameters, MACs, latency and energy of a candidate "
            "or of one of the paper's reference networks")
    s.add_argument("target", help="candidate YAML, a space of at most 16 candidates (e.g. paper), or a reference "
                   "network: fastdepth, fastdepth-pruned, s2d-resnet50, s2d-resnet18, monodepth2-resnet18, ...")
    s.add_argument("--input-size", type=_size, default=(224, 224), help="deployment resolution HxW (default 224x224)")
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--device", help="device profile name or YAML file")
    s.add_argument("--measure", action="store_true", help="also measure on this machine with onnxruntime "
                   "(--provider, --threads, --repeats)")
    s.add_argument("--threads", type=_bounded_int(1, MAX_THREADS, "threads"), default=None, help="onnxruntime threads (default: all cores)")
    s.add_argument("--repeats", type=int, default=20)
    _add_provider(s)
    s.add_argument("--json", action="store_true")

    s = add("anytime", cmd_anytime, "anytime loss (Eq. 1) of given per-path costs and losses")
    s.add_argument("--path", action="append", metavar="COST:LOSS", help="a path's cost (ms or J) and loss; repeat")
    s.add_argument("--budget", required=True, help="e.g. time:uniform:33ms, energy:uniform:0.5J")
    s.add_argument("--json", action="store_true")

    s = add("enumerate", cmd_enumerate, "cost every candidate of a space (no training)")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--device", default="tx2")
    s.add_argument("--budget", default="time:uniform:33ms")
    s.add_argument("--input-size", type=_size, default=(224, 224))
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--csv", help="CSV file to write the whole table to, one row per candidate (default: none)")
    s.add_argument("--parquet", help="Parquet file to write the whole table to (needs pyarrow; default: none)")
    s.add_argument("--front", default="p_path0,last_exit_ms,params",
                   help="columns to find the Pareto front of over every candidate, comma-separated, from params, "
                        "macs, first_exit_ms, last_exit_ms, first_exit_j, last_exit_j, p_path0 (the less the better), "
                        "p_last, budget_used (the more the better) (default p_path0,last_exit_ms,params)")
    s.add_argument("--top", type=int, default=20, help="front rows to print (default 20)")

    sp = add("data", None, "inspect a data set")
    dsub = sp.add_subparsers(dest="sub", required=True, parser_class=_Parser, metavar="SUBCOMMAND")
    s = dsub.add_parser("inspect", help="frames, shapes, depth range and path 0's metrics")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--lidar")
    s.add_argument("--split", default="val", choices=["train", "val"])
    s.add_argument("--input-size", type=_size, default=(224, 224), help="resolution HxW the frames are resized "
                   "to (default 224x224)")
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--frames", type=int, default=None, help="inspect at most this many frames (default: all)")
    deprecated_alias(s, "--limit", "--frames")
    s.add_argument("--out", help="PNG file: the first frame with its scan drawn over it (default: none)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_data_inspect)
