"""The ``explorer`` command line. Every mistake a user can make is one line on stderr, exit 2."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path
from typing import Sequence

from explorer.errors import UserError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + line)
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(2)


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not HxW (e.g. 224x224)") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"'{text}': sides must be positive")
    return h, w


def _count(text: str) -> float:
    """2.5M, 300k, 1500000."""
    t = text.strip().lower()
    mult = {"k": 1e3, "m": 1e6, "g": 1e9}.get(t[-1:], 1.0)
    try:
        return float(t[:-1] if t[-1:] in "kmg" else t) * mult
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a count (e.g. 2.5M)") from None


def _ms(text: str) -> float:
    from explorer.anytime import _parse_quantity
    try:
        return _parse_quantity(text, "time")
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _duration_s(text: str) -> float:
    t = text.strip().lower()
    units = {"s": 1, "m": 60, "h": 3600}
    try:
        return float(t[:-1]) * units[t[-1]] if t[-1:] in units else float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a duration (e.g. 10m, 90s, 1h)") from None


# -- commands -------------------------------------------------------------------------------------
def cmd_space_show(args) -> None:
    from explorer._console import console, print_json
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
    from explorer.space import Candidate, SearchSpace, resolve_space_path, _load_yaml
    p = resolve_space_path(path) if not Path(path).is_file() else Path(path)
    data = _load_yaml(p)
    if isinstance(data, dict) and "candidate" in data:
        return [Candidate.from_dict(data["candidate"], str(p))]
    space = SearchSpace.from_yaml(p)
    if space.size > 16:
        raise UserError(f"{p} has {space.size:,} candidates: profile takes a candidate file or a space of "
                        "at most 16 (use `explorer enumerate` for whole spaces)")
    return list(space.enumerate())


def _profile_reference(args, device) -> None:
    from explorer._console import console, print_frame, print_json
    from explorer.cost import profile_reference
    from explorer.model.reference import get_reference
    ref = get_reference(args.target)
    if args.measure:
        raise UserError("--measure works on candidates only; reference networks are costed, not measured")
    frame = profile_reference(ref.name, args.input, device)
    if args.json:
        published = ref.paper.__dict__ if ref.paper else None
        print_json({"reference": ref.name, "description": ref.description, "input_size": list(args.input),
                    "paths": frame.to_dict("records"), "published": published})
        return
    console.print(f"[bold]{ref.name}[/bold]  {ref.description}")
    print_frame(frame, f"at {args.input[0]}x{args.input[1]}" + (f" on {device.name}" if device else ""))


def cmd_profile(args) -> None:
    from explorer._console import console, print_frame, print_json
    from explorer.cost import get_device, profile_candidate
    from explorer.space import SPACES_DIR
    out = []
    device = get_device(args.device) if args.device else None
    looks_like_file = args.target.endswith((".yaml", ".yml")) or "/" in args.target
    if not looks_like_file and not Path(args.target).is_file() and not (SPACES_DIR / f"{args.target}.yaml").is_file():
        return _profile_reference(args, device)   # a reference network, or one line naming them
    for cand in _candidates_of(args.target):
        frame = profile_candidate(cand, args.input, device)
        entry = {"candidate": cand.to_dict(), "key": cand.key, "input_size": list(args.input),
                 "paths": frame.to_dict("records")}
        if args.measure:
            from explorer.cost.measure import measure_candidate
            m = measure_candidate(cand, args.input, threads=args.threads, repeats=args.repeats)
            frame["measured_ms"] = m.path_ms
            frame.loc[0, "measured_ms"] = 0.0
            entry["paths"] = frame.to_dict("records")
            entry["measured"] = {"stage_ms": m.stage_ms, "whole_graph_ms": m.whole_ms,
                                 "staged_total_ms": m.staged_total_ms, "staging_overhead": m.staging_overhead,
                                 "path0_ms": m.path_ms[0], "conditions": m.conditions}
        out.append(entry)
        if not args.json:
            console.print(f"[bold]{cand.key}[/bold]  {cand.describe()}")
            title = f"per path at {args.input[0]}x{args.input[1]}" + (f" on {device.name}" if device else "")
            print_frame(frame, title)
            if args.measure:
                console.print(f"whole graph {m.whole_ms:.3f} ms, sum of stages {m.staged_total_ms:.3f} ms "
                              f"({m.staging_overhead:+.1%}); onnxruntime {m.conditions['onnxruntime']}, "
                              f"{m.conditions['threads']} threads, median of {m.conditions['repeats']}")
    if args.json:
        print_json(out[0] if len(out) == 1 else out)


def cmd_anytime(args) -> None:
    from explorer._console import console, print_json
    from explorer.anytime import anytime_loss, interval_probabilities, parse_budget
    if not args.path:
        raise UserError("give at least one --path COST:LOSS (path 0 is added with cost 0 if missing)")
    pairs = []
    for text in args.path:
        try:
            c, l = text.split(":")
            pairs.append((float(c), float(l)))
        except ValueError:
            raise UserError(f"--path {text!r} is not COST:LOSS (e.g. 6.4:0.465)") from None
    pairs.sort()
    costs, losses = [p[0] for p in pairs], [p[1] for p in pairs]
    dist = parse_budget(args.budget)
    value = anytime_loss(costs, losses, dist)
    weights = interval_probabilities(costs, dist)
    if args.json:
        print_json({"budget": dist.spec, "anytime_loss": value, "costs": costs, "losses": losses,
                    "weights": list(weights)})
        return
    console.print(f"anytime loss for {dist.spec}: [bold]{value:.4f}[/bold]")
    for c, l, w in zip(costs, losses, weights):
        console.print(f"  path at {c:g} {dist.unit}: loss {l:g}, P(output) = {w:.4f}")


def cmd_devices(args) -> None:
    from explorer._console import console, print_json
    from explorer.cost.devices import available_devices, get_device
    if args.name:
        p = get_device(args.name)
        if args.json:
            print_json(p.to_dict())
        else:
            console.print(p.to_yaml(), markup=False, highlight=False)
        return
    rows = []
    for name in available_devices():
        p = get_device(name)
        fits = p.provenance.get("fit") or []
        err = fits[0].get("median_abs_error") if fits and "median_abs_error" in fits[0] else None
        rows.append({"name": name, "calibrated": p.calibrated, "latency": p.latency_basis,
                     "energy": p.energy_basis, "description": p.description, "fit_median_error": err})
    if args.json:
        print_json(rows)
        return
    console.print(f"  {'name':12s} {'latency':9s} {'energy':9s} description")
    for r in rows:
        err = f"  (fit error {r['fit_median_error']:.1%})" if r["fit_median_error"] is not None else ""
        console.print(f"  {r['name']:12s} {r['latency']:9s} {r['energy']:9s} {r['description']}{err}")
    console.print("  (measured: on the device; published: fitted to published figures; estimate: scaled from "
                  "another profile; none: not modelled)")
    console.print("  (any profile YAML file works too: --device ./mybox.yaml; make one with explorer calibrate)")


def cmd_calibrate(args) -> None:
    from explorer._console import console, progress
    from explorer.cost.calibrate import calibrate, fit_results, read_results
    if args.bundle and args.fit:
        raise UserError("--bundle writes graphs for a device, --fit reads what the probe measured there: give one")
    if args.bundle:
        from explorer.cost.bundle import write_bundle
        bundle = Path(args.bundle)
        if bundle.exists() and not args.force:
            raise UserError(f"{bundle} exists: pass --force to overwrite it")
        with progress() as bar:
            task = bar.add_task("exporting graphs", total=None, status="")
            manifest = write_bundle(bundle, scale=0.35 if args.quick else 1.0, repeats=args.repeats,
                                    progress=lambda i, n: bar.update(task, completed=i, total=n))
        console.print(f"wrote {bundle} ({bundle.stat().st_size / 1e6:.1f} MB, {len(manifest['layers'])} layer "
                      f"graphs, {len(manifest['candidates'])} candidates' stages, bundle {manifest['id']}); on the "
                      f"device: tar xf {bundle.name} && python3 probe.py --out results.json")
        return
    if not args.out:
        raise UserError("give --out PROFILE.yaml (or --bundle FILE to measure another device)")
    out = Path(args.out)
    if out.exists() and not args.force:
        raise UserError(f"{out} exists: pass --force to overwrite it")
    if args.fit:
        prof = fit_results(read_results(args.fit), name=args.name or out.stem)
    else:
        from explorer.cost.probe_script import ProbeError, check_provider
        try:
            check_provider(args.provider)  # before the progress bar: one line, nothing else
        except ProbeError as exc:
            raise UserError(str(exc)) from None
        with progress() as bar:
            task = bar.add_task("measuring layers", total=None, status="")
            prof = calibrate(threads=args.threads, repeats=args.repeats, scale=0.35 if args.quick else 1.0,
                             name=args.name or out.stem, provider=args.provider, energy=args.energy,
                             progress=lambda i, n: bar.update(task, completed=i, total=n),
                             log=lambda s: bar.console.print(s))
    out.parent.mkdir(parents=True, exist_ok=True)
    how = f"from {args.fit}" if args.fit else "on this machine"
    out.write_text(f"# Made by `explorer calibrate` {how}.\n" + prof.to_yaml())
    console.print(f"wrote {out}")
    for fit in prof.provenance["fit"]:
        console.print(f"  fit on {fit['what']}: median error {fit['median_abs_error']:.1%}, "
                      f"{fit['within_10pct']:.0%} within 10%")
    console.print(f"  energy: {prof.provenance['energy_note']}")


def cmd_enumerate(args) -> None:
    from explorer._console import console, print_frame, progress
    from explorer.enumerate import enumerate_space
    from explorer.space import SearchSpace
    space = SearchSpace.from_yaml(args.space)
    t0 = time.perf_counter()
    with progress(transient=True) as bar:
        task = bar.add_task(f"costing {space.name}", total=space.size, status="")
        frame = enumerate_space(space, args.device, args.budget, args.input,
                                progress=lambda i, n: bar.update(task, completed=i))
    dt = time.perf_counter() - t0
    if args.csv:
        Path(args.csv).parent.mkdir(parents=True, exist_ok=True)
        frame.to_csv(args.csv, index=False)
        console.print(f"wrote {len(frame):,} candidates to {args.csv}")
    console.print(f"{len(frame):,} candidates costed in {dt:.1f} s ({len(frame) / dt:,.0f}/s)")
    cols = ["key", "params", "macs", "paths", "first_exit_ms", "last_exit_ms", "p_path0"]
    print_frame(frame.nsmallest(10, "p_path0")[cols], "fewest halts left to path 0")


def cmd_data_inspect(args) -> None:
    import numpy as np
    from explorer._console import console, print_json, progress
    from explorer.data import open_dataset
    from explorer.metrics import MetricAverager, depth_metrics
    from explorer.model import interpolate_scan
    with progress(transient=True) as bar:
        task = bar.add_task("generating synthetic scenes", total=None, status="")
        ds = open_dataset(args.data, args.split, args.input, train_augment=False,
                          progress=lambda i, n: bar.update(task, completed=i, total=n))
    n = len(ds) if not args.limit else min(args.limit, len(ds))
    if n == 0:
        raise UserError(f"data {args.data}: the {args.split} split is empty")
    avg, dmin, dmax, valid, scan_valid = MetricAverager(), np.inf, 0.0, [], []
    for i in range(n):
        item = ds[i]
        d = item["depth"]
        pos = d[d > 0]
        if pos.numel():
            dmin, dmax = min(dmin, float(pos.min())), max(dmax, float(pos.max()))
        valid.append(float((d > 0).float().mean()))
        scan_valid.append(float((item["scan"] > 0).float().mean()))
        p0 = interpolate_scan(item["scan"][None], d.shape[1])[0]
        avg.add(depth_metrics(p0, d))
    res = {"data": str(ds.name), "split": args.split, "frames": len(ds), "inspected": n,
           "input_size": list(args.input), "image_shape": list(item["image"].shape),
           "depth_range_m": [dmin, dmax], "valid_depth_fraction": float(np.mean(valid)),
           "scan_return_fraction": float(np.mean(scan_valid)), "scan_row": item["scan_row"],
           "path0": avg.result()}
    if args.json:
        print_json(res)
        return
    console.print(f"[bold]{res['data']}[/bold] {args.split}: {len(ds)} frames (inspected {n}) at "
                  f"{args.input[0]}x{args.input[1]}")
    console.print(f"  depth {dmin:.2f}-{dmax:.2f} m, {res['valid_depth_fraction']:.1%} of pixels valid; "
                  f"scan row {res['scan_row']}, {res['scan_return_fraction']:.1%} of columns with a return")
    p0 = res["path0"]
    console.print(f"  path 0 (scan, nearest): RMSE {p0['rmse']:.3f} m, REL {p0['rel']:.3f}, "
                  f"delta1 {p0['delta1']:.3f}")


def cmd_train(args) -> None:
    import dataclasses
    from explorer._console import console, print_frame, progress
    from explorer.data import open_dataset
    from explorer.model import build_network
    from explorer.train import RECIPES, check_data_for, load_encoder_weights, resolve_device, train
    candidate = _candidates_of(args.candidate)
    if len(candidate) != 1:
        raise UserError(f"{args.candidate} holds {len(candidate)} candidates: train takes one")
    candidate = candidate[0]
    cfg = RECIPES[args.recipe]
    changes = {k: v for k, v in (("steps", args.steps), ("batch_size", args.batch_size),
                                 ("input_size", args.input_size), ("lr", args.lr), ("seed", args.seed))
               if v is not None}
    cfg = dataclasses.replace(cfg, **changes, supervision=args.supervision, poses=args.poses,
                              scan_loss=not args.no_scan_loss)
    cfg.validate()
    device = resolve_device(args.accelerator)
    with progress(transient=True) as bar:
        task = bar.add_task("generating synthetic scenes (once, then cached)", total=None, status="")
        train_set = open_dataset(args.data, "train", cfg.input_size, seed=cfg.seed,
                                 progress=lambda i, n: bar.update(task, completed=i, total=n))
    val_set = open_dataset(args.data, "val", cfg.input_size, train_augment=False)
    check_data_for(cfg, train_set)
    import torch
    torch.manual_seed(cfg.seed)
    net = build_network(candidate)
    if args.encoder_weights:
        n = load_encoder_weights(net, args.encoder_weights)
        console.print(f"loaded {n} encoder tensors from {args.encoder_weights}")
    out = Path(args.out or f"reports/checkpoints/{candidate.key}.pt")
    with progress() as bar:
        task = bar.add_task(f"training ({cfg.supervision})", total=cfg.steps, status="")
        result = train(net, train_set, val_set, cfg, device, checkpoint=out,
                       progress=lambda s, n, r: bar.update(task, completed=s, status=f"loss {r['loss']:.3f}"))
    console.print(f"saved {out} ({result.steps} steps, {result.images_per_second:.1f} images/s)")
    print_frame(result.metrics, "validation, per path" + ("" if cfg.metric else " (median-scaled: no scan term)"))


def cmd_evaluate(args) -> None:
    from explorer._console import print_frame, print_json
    from explorer.data import open_dataset
    from explorer.train import TrainConfig, evaluate, network_from_checkpoint
    net, state = network_from_checkpoint(args.checkpoint)
    recipe = TrainConfig.from_dict(state["train_config"])
    size = args.input or recipe.input_size
    ds = open_dataset(args.data, args.split, size, train_augment=False)
    # a depth known only up to scale (self-supervised without the scan term) is median-scaled
    frame = evaluate(net, ds, limit=args.limit, median_scaling=not recipe.metric)
    if args.json:
        print_json({"checkpoint": args.checkpoint, "data": str(ds.name), "input_size": list(size),
                    "supervision": recipe.supervision, "median_scaling": not recipe.metric,
                    "paths": frame.to_dict("records")})
    else:
        print_frame(frame[["path", "rmse", "mae", "rel", "delta1", "delta2", "delta3"]],
                    f"{args.checkpoint} on {ds.name} ({args.split}) at {size[0]}x{size[1]}")


def cmd_search(args) -> None:
    import optuna
    from explorer._console import err_console, progress
    from explorer.search import SearchConfig, search
    from explorer.space import SearchSpace
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    space_name = SearchSpace.from_yaml(args.space).name
    study = args.study or f"{Path(str(args.device)).stem}-{space_name}"
    cfg = SearchConfig(
        study=study, space=args.space, device=args.device, budgets=tuple(args.budget or ["time:uniform:33ms"]),
        data=args.data, objectives=tuple(args.objectives.split(",")), metric=args.metric,
        input_size=args.input_size, train_size=args.train_size, train_steps=args.train_steps,
        batch_size=args.batch_size, seed=args.seed, max_params=args.max_params,
        max_first_exit_ms=args.max_first_exit, baselines=not args.no_baselines,
        pruning=not args.no_pruning, keep_weights=not args.no_weights, accelerator=args.accelerator,
        evaluator=args.evaluator, supernet=args.supernet, supernet_steps=args.supernet_steps,
        finalists=args.finalists, finalist_steps=args.finalist_steps,
        max_retries=args.max_retries,
        supervision=args.supervision)
    cfg.validate()
    reports = Path(args.reports)
    timeout = None if args.timeout == 0 else args.timeout
    total = args.trials
    t0 = time.time()
    with progress(transient=True) as bar:
        task = bar.add_task(f"search {study}", total=total, status="starting (data, baselines)")
        phases: dict = {}

        def supernet(step: int, steps: int, record: dict) -> None:
            if "supernet" not in phases:
                phases["supernet"] = bar.add_task("supernet (once per space, data, recipe)", total=steps, status="")
            bar.update(phases["supernet"], completed=step, status=f"largest {record['largest']:.3f}, "
                       f"smallest {record['smallest']:.3f}")

        def finalist(i: int, n: int, what: str) -> None:
            if "finalists" not in phases:
                phases["finalists"] = bar.add_task("finalists (retraining)", total=n, status="")
            bar.update(phases["finalists"], completed=i, status=what)

        def show(study_obj, trial=None) -> None:
            nonlocal t0
            if "search_start" not in phases:
                phases["search_start"], t0 = True, time.time()
            from explorer.retry import counted_trials
            complete = study_obj.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            complete = [t for t in complete if t.values]
            best = min((t.values[0] for t in complete), default=float("nan"))
            last = f"trial {trial.number} {trial.state.name.lower()}" + (
                f" {trial.values[0]:.4f}" if trial is not None and trial.values else "") if trial else ""
            left = "" if timeout is None else f", {max(timeout - (time.time() - t0), 0) / 60:.1f} min left"
            bar.update(task, completed=counted_trials(study_obj), status=f"{last}  best {best:.4f}{left}")

        def data(i: int, n: int) -> None:
            bar.update(task, status=f"generating synthetic scenes {i}/{n} (once, then cached)")

        outcome = search(cfg, storage_url=args.storage, workers=args.workers, n_trials=total,
                         timeout_s=timeout, reports=reports, on_trial=show, on_poll=show, on_data=data,
                         on_supernet=supernet, on_finalist=finalist)
    if outcome.interrupted_failed:
        err_console.print(f"marked {outcome.interrupted_failed} interrupted trial(s) as failed")
    _print_retries(outcome, cfg)
    _print_outcome(outcome.study, cfg, outcome.storage_url, reports, args.report)


def _print_retries(outcome, cfg) -> None:
    from explorer._console import err_console
    from explorer.results import BASELINE_LABELS
    trials = {t.number: t for t in outcome.study.get_trials(deepcopy=False)}
    def what(n: int) -> str:
        b = trials[n].user_attrs.get("baseline") if n in trials else None
        return f"trial {n}" + (f" ({BASELINE_LABELS.get(b, b)})" if b else "")
    for old, new in outcome.retried.items():
        err_console.print(f"{what(old)} was interrupted: tried again as trial {new}")
    for old in outcome.not_retried:
        err_console.print(f"{what(old)} was interrupted and is not tried again (--max-retries {cfg.max_retries} "
                          "reached)")


def _print_outcome(study, cfg, storage_url: str, reports: Path, write_report: bool) -> None:
    import optuna
    from explorer._console import console, print_frame
    from explorer.cost import get_device
    from explorer.results import (baseline_trial, best_trial, finalists_frame, is_retrained, missing_baselines,
                                  path_table, winner)
    from explorer.space import Candidate
    states = [t.state for t in study.get_trials(deepcopy=False)]
    count = {s.name.lower(): states.count(s) for s in optuna.trial.TrialState if states.count(s)}
    console.print(f"study [bold]{cfg.study}[/bold]: " + ", ".join(f"{v} {k}" for k, v in count.items()))
    best, estimate = winner(study), best_trial(study)
    if best is None:
        console.print("no candidate trial completed yet: run longer (--timeout / --trials)")
    else:
        retrained = is_retrained(best)
        cand = Candidate.from_dict(best.user_attrs["candidate"])
        how = "retrained" if retrained else f"estimated ({(best.user_attrs.get('evaluator') or {}).get('evaluator', 'proxy')})"
        console.print(f"winner: trial {best.number} ({cand.key}) anytime loss [bold]{best.values[0]:.4f}[/bold] "
                      f"{how}, for {cfg.budgets[0]} on {cfg.device}")
        console.print(f"  {cand.describe()}")
        print_frame(path_table(best, [get_device(cfg.device)]), "winner, per path")
        fin = finalists_frame(study)
        if not fin.empty:
            cols = ["model", "candidate_key", "estimated", "retrained", "estimated_rank", "retrained_rank"]
            print_frame(fin[cols], f"finalists: search estimate vs retrained ({cfg.finalist_steps} steps)")
        paper = baseline_trial(study, "paper", retrained=retrained)
        if paper is not None:
            kind = "retrained " if retrained else ""
            console.print(f"ratio to the {kind}paper-design baseline ({paper.values[0]:.4f}): "
                          f"[bold]{best.values[0] / paper.values[0]:.3f}[/bold]")
        if retrained and estimate is not None and estimate.number != best.user_attrs["finalist"].get("estimate_trial"):
            console.print(f"  (the search's best estimate was trial {estimate.number}; retraining ranked another first)")
    # a missing comparison is said, with why, never dropped silently
    missing = missing_baselines(study)
    if missing and all("--no-baselines" in m["why"] for m in missing):
        console.print("no baselines (the study was created with --no-baselines): no ratio to the paper design")
    else:
        for m in missing:
            lead = "no ratio to the paper-design baseline:" if m["name"] == "paper" and best is not None \
                else f"baseline {m['label']} missing:"
            console.print(f"{lead} {m['why']}", markup=False, highlight=False)
    console.print(f"study: {storage_url}")
    if write_report:
        try:
            from explorer.report import write_report as _write
        except ImportError:
            return
        path = _write(study, out_dir=reports / cfg.study)
        console.print(f"report: {path}")


def cmd_supernet_train(args) -> None:
    from explorer._console import console, progress
    from explorer.space import SearchSpace
    from explorer.supernet import SupernetRecipe, default_path, train_supernet
    from explorer.supernet.train import read
    from explorer.train import resolve_device
    space = SearchSpace.from_yaml(args.space)
    if args.steps < 1 or args.random_subnets < 0 or args.micro_batches < 1 or args.batch_size < 1:
        raise UserError("--steps, --batch-size and --micro-batches must be at least 1, --random-subnets at least 0")
    recipe = SupernetRecipe(steps=args.steps, batch_size=args.batch_size, input_size=args.input_size, lr=args.lr,
                            lr_end=args.lr / 10, random_subnets=args.random_subnets,
                            micro_batches=args.micro_batches, seed=args.seed)
    out = Path(args.out) if args.out else default_path(space, args.data, recipe)
    with progress() as bar:
        task = bar.add_task("supernet", total=recipe.steps, status="")
        data = bar.add_task("data", total=None, status="", visible=False)
        path = train_supernet(
            space, args.data, recipe, out, resolve_device(args.accelerator),
            progress=lambda s, n, r: bar.update(task, completed=s, status=f"largest {r['largest']:.3f}, "
                                                f"smallest {r['smallest']:.3f}, random {r['random']:.3f}"),
            data_progress=lambda i, n: bar.update(data, completed=i, total=n, visible=True,
                                                  description="generating synthetic scenes (once)"),
            checkpoint_every=max(args.checkpoint_every, 1), max_steps=args.max_steps)
    state = read(path)
    console.print(f"supernet of {space.name}: {path} (step {state['step']}/{recipe.steps}, "
                  f"{state['seconds'] / 60:.1f} min of training)")


def cmd_supernet_show(args) -> None:
    from explorer._console import console, print_json
    from explorer.supernet.train import read
    state = read(args.file)
    info = {k: state[k] for k in ("space_name", "space_key", "data", "recipe", "step", "complete", "seconds")}
    info["last"] = state["history"][-1] if state.get("history") else None
    if args.json:
        print_json(info)
        return
    console.print(f"{args.file}: space {info['space_name']} ({info['space_key']}), data {info['data']}, "
                  f"step {info['step']}/{info['recipe']['steps']}{' (complete)' if info['complete'] else ''}, "
                  f"{info['seconds'] / 60:.1f} min")
    console.print(f"  recipe: {info['recipe']}")


def cmd_rescore(args) -> None:
    from explorer._console import print_frame, print_json
    from explorer.results import rescore
    from explorer.storage import load_study
    study = load_study(args.study, args.storage, Path(args.reports))
    frame = rescore(study, args.device, args.budget, args.metric)
    if frame.empty:
        raise UserError(f"study '{args.study}' has no completed trial to re-score yet")
    if args.csv:
        frame.to_csv(args.csv, index=False)
    if args.json:
        print_json(frame.to_dict("records"))
    else:
        print_frame(frame.head(args.top), f"{args.study} re-scored for {args.device} (sorted by {args.budget[0]})")


def cmd_report(args) -> None:
    from explorer._console import console
    from explorer.report import write_report
    from explorer.storage import load_study
    study = load_study(args.study, args.storage, Path(args.reports))
    out = Path(args.out) if args.out else Path(args.reports) / args.study
    path = write_report(study, out_dir=out, devices=args.device, budgets=args.budget, data=args.data,
                        curve=Path(args.curve) if args.curve else None)
    console.print(f"report: {path}")


def cmd_export(args) -> None:
    from explorer._console import console
    from explorer.deploy import export_from_checkpoint, export_from_study
    if bool(args.study) == bool(args.checkpoint):
        raise UserError("give either --study S (optionally --trial N) or --checkpoint FILE")
    if args.study:
        manifest = export_from_study(args.study, args.trial, Path(args.out), args.storage,
                                     Path(args.reports), args.input, args.device)
    else:
        manifest = export_from_checkpoint(Path(args.checkpoint), Path(args.out), args.input, args.device)
    console.print(f"exported {len(manifest['stages'])} stage graphs to {args.out} "
                  f"(max |onnx - torch| {manifest['verification']['max_abs_diff']:.2e})")


def cmd_run(args) -> None:
    from explorer._console import console, print_json
    from explorer.runtime import run_files
    res = run_files(Path(args.model), Path(args.image), Path(args.scan), args.deadline,
                    Path(args.out) if args.out else None, args.threads, args.provider)
    if args.json:
        print_json(res)
        return
    console.print(f"returned path {res['path']} (ready at {res['ready_ms']:.2f} ms, deadline {args.deadline:g} ms); "
                  f"{res['completed_paths']} path(s) completed" + (f"; wrote {args.out}" if args.out else ""))


def cmd_curve(args) -> None:
    from explorer._console import console, print_json, progress
    from explorer.runtime import curve_check
    with progress(transient=True) as bar:
        task = bar.add_task("deadlines", total=args.deadlines, status="")
        res = curve_check(Path(args.model), args.data, args.device, args.frames, args.deadlines,
                          progress=lambda i, n: bar.update(task, completed=i), provider=args.provider)
    if args.json:
        print_json(res)
        return
    m, p = res["measured_anytime_loss"], res["predicted_anytime_loss"]
    console.print(f"anytime loss U(0, {res['b_max_ms']:.1f} ms) on this machine: measured {m:.4f}, predicted by "
                  f"{res['device']} {p:.4f} ({m / p - 1:+.1%}); written to {Path(args.model) / 'anytime_curve.json'}")


# -- parser ---------------------------------------------------------------------------------------
def _add_supervision(s: argparse.ArgumentParser) -> None:
    s.add_argument("--supervision", default="supervised", choices=["supervised", "self", "mixed"],
                   help="supervised: L1 on dense depth (default); self: photometric reprojection between "
                   "neighbouring frames plus the scan row for metric scale (needs sequence data: "
                   "synthetic-seq, kitti-seq:DRIVE, frames:FOLDER); mixed: both where labels exist")


def build_parser() -> argparse.ArgumentParser:
    from explorer import __version__
    p = _Parser(prog="explorer", description="Hardware-aware design-space explorer for anytime depth estimation "
                "(camera + 2D LiDAR): search early-exit networks for the lowest anytime loss on a device.")
    p.add_argument("--version", action="version", version=f"anytime-explorer {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")

    def add(name, fn, help_):
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(fn=fn)
        return sp

    reports = dict(default="reports", help="where studies live (default: reports/)")

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
    s.add_argument("--input-size", "--input", dest="input", type=_size, default=(224, 224),
                   help="input HxW (default 224x224)")
    s.add_argument("--device", help="device profile name or YAML file")
    s.add_argument("--measure", action="store_true", help="also measure on this machine with onnxruntime")
    s.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    s.add_argument("--repeats", type=int, default=20)
    s.add_argument("--json", action="store_true")

    s = add("anytime", cmd_anytime, "anytime loss (Eq. 1) of given per-path costs and losses")
    s.add_argument("--path", action="append", metavar="COST:LOSS", help="a path's cost (ms or J) and loss; repeat")
    s.add_argument("--budget", required=True, help="e.g. time:uniform:33ms, energy:uniform:0.5J")
    s.add_argument("--json", action="store_true")

    s = add("devices", cmd_devices, "list device profiles, or show one with its provenance")
    s.add_argument("action", nargs="?", choices=["show"], help="show one profile")
    s.add_argument("name", nargs="?", help="profile name or file")
    s.add_argument("--json", action="store_true")

    s = add("calibrate", cmd_calibrate, "measure this machine with onnxruntime and write a device profile; "
            "or pack the measurement for another device (--bundle) and fit what it measured (--fit)")
    s.add_argument("--out", help="profile YAML to write")
    s.add_argument("--bundle", metavar="FILE.tar", help="write the graphs and probe.py (needs only python3, numpy "
                   "and onnxruntime) for a device, instead of measuring here")
    s.add_argument("--fit", metavar="RESULTS.json", help="fit --out to what probe.py measured on a device")
    s.add_argument("--name", help="profile name (default: the file's stem)")
    s.add_argument("--threads", type=int, default=None)
    s.add_argument("--repeats", type=int, default=25)
    s.add_argument("--provider", default="CPUExecutionProvider", help="onnxruntime execution provider "
                   "(default CPUExecutionProvider; CUDA, TensorRT, OpenVINO, XNNPACK ones where installed)")
    s.add_argument("--no-energy", dest="energy", action="store_false", help="do not sample power sensors")
    s.add_argument("--quick", action="store_true", help="a third of the sweep (for a first look)")
    s.add_argument("--force", action="store_true", help="overwrite --out or --bundle")

    s = add("enumerate", cmd_enumerate, "cost every candidate of a space (no training)")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--device", default="tx2")
    s.add_argument("--budget", default="time:uniform:33ms")
    s.add_argument("--input-size", "--input", dest="input", type=_size, default=(224, 224))
    s.add_argument("--csv", help="write the table here")

    sp = add("data", None, "inspect a data set")
    dsub = sp.add_subparsers(dest="sub", required=True, parser_class=_Parser, metavar="SUBCOMMAND")
    s = dsub.add_parser("inspect", help="frames, shapes, depth range and path 0's metrics")
    s.add_argument("--data", default="synthetic", help="synthetic | nyu:PATH | kitti:PATH | synthetic-seq | "
                   "kitti-seq:DRIVE | frames:FOLDER")
    s.add_argument("--split", default="val", choices=["train", "val"])
    s.add_argument("--input-size", "--input", dest="input", type=_size, default=(224, 224))
    s.add_argument("--limit", type=int, default=None, help="inspect at most this many frames")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_data_inspect)

    s = add("train", cmd_train, "train a candidate (all exits) and save a checkpoint")
    s.add_argument("candidate", help="candidate YAML or one-point space (e.g. paper)")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--recipe", default="proxy", choices=["proxy", "paper"])
    s.add_argument("--steps", type=int)
    s.add_argument("--batch-size", type=int)
    s.add_argument("--input-size", type=_size)
    s.add_argument("--lr", type=float)
    s.add_argument("--seed", type=int)
    s.add_argument("--encoder-weights", help="MobileNet v1 state dict file to start the encoder from")
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--out", help="checkpoint path (resumes if it exists)")
    _add_supervision(s)
    s.add_argument("--poses", default="net", choices=["net", "given"],
                   help="self-supervision's camera motion: a pose network trained jointly (default), or "
                   "the data's own poses (synthetic-seq, KITTI oxts, a folder's poses.txt)")
    s.add_argument("--no-scan-loss", action="store_true",
                   help="self-supervision without the L1 term on the scan row: depth only up to scale, "
                   "evaluated with median scaling")

    s = add("evaluate", cmd_evaluate, "per-path metrics of a checkpoint on a data set")
    s.add_argument("checkpoint")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--split", default="val", choices=["train", "val"])
    s.add_argument("--input-size", "--input", dest="input", type=_size, help="input HxW (default: the training size)")
    s.add_argument("--limit", type=int)
    s.add_argument("--json", action="store_true")

    s = add("search", cmd_search, "search the space for the lowest anytime loss on a device")
    s.add_argument("--device", default="tx2", help="profile name or YAML (default tx2)")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--budget", action="append", help="repeatable; the first is the objective "
                   "(default time:uniform:33ms)")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--study", help="study name (default DEVICE-SPACE); the same name resumes")
    s.add_argument("--storage", help="Optuna storage URL (default reports/<study>/study.db; "
                   "postgresql://... for several machines)")
    s.add_argument("--workers", type=int, default=1, help="processes on this machine (journal storage)")
    s.add_argument("--timeout", type=_duration_s, default=300.0, help="stop sampling after this long (default 5m; "
                   "0 = none; the supernet's training and the finalists come on top)")
    s.add_argument("--trials", type=int, default=None, help="stop after this many finished trials")
    s.add_argument("--objectives", default="anytime_loss", help="e.g. anytime_loss,params (NSGA-II)")
    s.add_argument("--metric", default="rmse", choices=["rmse", "mae", "rel"])
    s.add_argument("--max-params", type=_count, help="reject candidates above this, e.g. 2.5M")
    s.add_argument("--max-first-exit", type=_ms, help="reject candidates whose first exit is later, e.g. 10ms")
    s.add_argument("--evaluator", default="supernet", choices=["supernet", "proxy"],
                   help="how a candidate's accuracy is estimated: its slice of the space's supernet (trained "
                   "once, then ~1 s a candidate; default) or proxy training alone (~20 s a candidate)")
    s.add_argument("--supernet", help="supernet file (default: the one cached for space, data and recipe, "
                   "trained first if missing)")
    s.add_argument("--supernet-steps", type=int, default=1000, help="supernet training steps (default 1000)")
    s.add_argument("--finalists", type=int, default=3, help="best distinct candidates retrained stand-alone "
                   "at the end, next to the baselines (default 3; 0 = none)")
    s.add_argument("--finalist-steps", type=int, default=300, help="steps of the finalists' longer recipe "
                   "(default 300)")
    s.add_argument("--train-steps", type=int, default=150, help="proxy recipe steps (default 150)")
    s.add_argument("--train-size", type=_size, default=(64, 64), help="training resolution (default 64x64)")
    s.add_argument("--batch-size", type=int, default=16)
    s.add_argument("--input-size", "--input", type=_size, default=(224, 224),
                   help="deployment resolution for costs (default 224x224)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--no-baselines", action="store_true")
    s.add_argument("--max-retries", type=int, default=2, help="try an interrupted trial (killed, Ctrl-C, "
                   "lost worker) again at most this many times (default 2); a trial that fails is not")
    s.add_argument("--no-pruning", action="store_true")
    s.add_argument("--no-weights", action="store_true", help="do not keep trained weights as artifacts")
    s.add_argument("--no-report", dest="report", action="store_false", help="skip the HTML report")
    _add_supervision(s)
    s.add_argument("--reports", **reports)

    sp = add("supernet", None, "train or inspect the weight-sharing supernet of a space")
    nsub = sp.add_subparsers(dest="sub", required=True, parser_class=_Parser, metavar="SUBCOMMAND")
    s = nsub.add_parser("train", help="train (or resume) a supernet: sandwich rule, in-place distillation",
                        description="Train the supernet of a space once; every study on that space, data and "
                        "recipe reuses it. Resumes after a kill. Data parallel under torchrun "
                        "(torchrun --nproc_per_node N -m explorer supernet train ...).")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--steps", type=int, default=1000)
    s.add_argument("--input-size", "--input", dest="input_size", type=_size, default=(64, 64),
                   help="training resolution (default 64x64)")
    s.add_argument("--batch-size", type=int, default=16, help="global batch (over all processes)")
    s.add_argument("--lr", type=float, default=2e-3)
    s.add_argument("--random-subnets", type=int, default=2, help="random subnets per step besides the largest "
                   "and the smallest (default 2)")
    s.add_argument("--micro-batches", type=int, default=1, help="split each process's batch (gradient "
                   "accumulation; BatchNorm statistics per micro-batch)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--out", help="file (default: the cache, where searches find it)")
    s.add_argument("--checkpoint-every", type=int, default=100, help="steps between checkpoints (default 100)")
    s.add_argument("--max-steps", type=int, help="stop after this many steps in this run (resume later)")
    s.set_defaults(fn=cmd_supernet_train)
    s = nsub.add_parser("show", help="what a supernet file holds: space, data, recipe, progress")
    s.add_argument("file")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_supernet_show)

    s = add("rescore", cmd_rescore, "rank a finished study's trials for another device or budget")
    s.add_argument("--study", required=True)
    s.add_argument("--storage")
    s.add_argument("--device", required=True)
    s.add_argument("--budget", action="append", required=True)
    s.add_argument("--metric", default="rmse", choices=["rmse", "mae", "rel"])
    s.add_argument("--top", type=int, default=15)
    s.add_argument("--csv")
    s.add_argument("--json", action="store_true")
    s.add_argument("--reports", **reports)

    s = add("report", cmd_report, "write a study's self-contained HTML report")
    s.add_argument("--study", required=True)
    s.add_argument("--storage")
    s.add_argument("--device", action="append", help="devices for the tables (default: the study's)")
    s.add_argument("--budget", action="append", help="budgets for the tables (default: a standard set)")
    s.add_argument("--data", help="data set for the depth-map figure (default: the study's)")
    s.add_argument("--out", help="folder (default reports/<study>/)")
    s.add_argument("--curve", help="anytime_curve.json from explorer curve (default: OUT/export/ if there)")
    s.add_argument("--reports", **reports)

    s = add("export", cmd_export, "export a trained candidate as ONNX stage graphs + manifest")
    s.add_argument("--study")
    s.add_argument("--trial", type=int, help="trial number (default: the best)")
    s.add_argument("--checkpoint", help="export a checkpoint instead of a study trial")
    s.add_argument("--storage")
    s.add_argument("--out", required=True)
    s.add_argument("--input-size", "--input", dest="input", type=_size, default=None,
                   help="input HxW (default: the study's input size)")
    s.add_argument("--device", action="append", help="devices whose expected costs go in the manifest")
    s.add_argument("--reports", **reports)

    s = add("run", cmd_run, "run an exported model under a deadline and return the best depth map")
    s.add_argument("model", help="folder written by explorer export")
    s.add_argument("--image", required=True)
    s.add_argument("--scan", required=True, help=".csv or .npy: one depth (m) per image column, 0 = none")
    s.add_argument("--deadline", type=_ms, required=True, help="e.g. 8ms")
    s.add_argument("--out", help="write the depth map (.png 16-bit mm, or .npy metres)")
    s.add_argument("--threads", type=int, default=None)
    s.add_argument("--provider", default="CPUExecutionProvider", help="onnxruntime execution provider "
                   "(default CPUExecutionProvider)")
    s.add_argument("--json", action="store_true")

    s = add("curve", cmd_curve, "measure an exported model's anytime curve here and compare with the prediction")
    s.add_argument("model", help="folder written by explorer export")
    s.add_argument("--data", default="synthetic", help="frames to measure on (validation split)")
    s.add_argument("--device", help="host profile from explorer calibrate (default: calibrate now)")
    s.add_argument("--frames", type=int, default=16)
    s.add_argument("--deadlines", type=int, default=40)
    s.add_argument("--provider", default="CPUExecutionProvider", help="onnxruntime execution provider "
                   "(default CPUExecutionProvider)")
    s.add_argument("--json", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    warnings.filterwarnings("ignore", category=UserWarning, module="torch")
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "devices" and args.action == "show" and not args.name:
        parser.error("devices show needs a NAME")
    if args.command == "devices" and args.name and not args.action:
        args.name, args.action = args.name, "show"
    try:
        args.fn(args)
    except UserError as exc:
        sys.stderr.write(f"explorer: error: {exc}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("explorer: interrupted; finished trials and checkpoints are kept\n")
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
