"""``explorer search``, ``rescore`` and ``report``: running a study and reading it."""

from __future__ import annotations

import time
from pathlib import Path

from explorer.errors import UserError
from explorer.cli._common import (HEAD_KINDS, MAX_WORKERS, _add_supervision, _bounded_int, _count, _duration_s, _ms,
                                  _size, deprecated_alias, train_on_free_cores, write_output)


def cmd_search(args) -> None:
    import optuna
    from explorer.cli._search_progress import SearchProgress
    from explorer.console import err_console, progress
    from explorer.study.run import SearchRun
    from explorer.study.search import search
    from explorer.study.view import study_view
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    started = time.time()  # the time limit counts from here: data generation is part of the run
    context = _search_context(args)
    cfg, reports = context.config, Path(args.reports)
    timeout, limit = _time_limits(args, started)
    run = SearchRun(storage_url=args.storage, workers=args.workers, n_trials=args.trials, timeout_s=timeout,
                    time_limit=limit, reports=reports)
    train_on_free_cores()
    with progress(transient=True) as bar:
        shown = SearchProgress(bar, cfg.study, args.trials, timeout)
        if limit is not None:
            bar.update(shown.task, status="measuring this machine for --time-limit (a few training steps)")
        outcome = search(context, run, shown)
    cfg = outcome.config or cfg
    if outcome.interrupted_failed:
        err_console.print(f"marked {outcome.interrupted_failed} interrupted trial(s) as failed")
    _print_retries(outcome, cfg)
    _print_outcome(study_view(outcome.study), cfg, outcome.storage_url, reports, args.report)


def _search_context(args):
    """The study's settings from the command line, resolved (its space, device and budgets) and checked,
    once; a study not named is named DEVICE-SPACE. A device or budget not given is the settings' default."""
    import dataclasses

    from explorer.study.config import SearchConfig
    given = {"device": args.device, "budgets": tuple(args.budget) if args.budget else None}
    cfg = SearchConfig(
        study=args.study or "", space=args.space, **{k: v for k, v in given.items() if v is not None},
        data=args.data, objectives=tuple(args.objectives.split(",")), metric=_metric(args),
        input_size=args.input_size, train_size=args.train_size, train_steps=args.proxy_steps,
        batch_size=args.batch_size, amp=args.amp, head_kinds=args.head_kinds, seed=args.seed,
        max_params=args.max_params,
        max_first_exit_ms=args.max_first_exit, baselines=_baselines(args),
        pruning=not args.no_pruning, keep_weights=not args.no_weights, accelerator=args.accelerator,
        evaluator=args.evaluator, sampler=args.sampler, supernet=args.supernet,
        supernet_steps=600 if args.supernet_steps is None else args.supernet_steps,
        finalists=3 if args.finalists is None else args.finalists,
        finalist_steps=300 if args.finalist_steps is None else args.finalist_steps, tune_steps=args.tune_steps,
        max_retries=args.max_retries,
        supervision=args.supervision, poses=args.poses, hints=args.depth_hints, self_distill=args.self_distill)
    context = cfg.resolve()
    if not args.study:
        named = f"{Path(str(cfg.device)).stem}-{context.space.name}"
        context = context.with_config(dataclasses.replace(cfg, study=named))
    return context


def _metric(args) -> str:
    """The study's ``--metric``: as given, else the data's default (said where it is not RMSE)."""
    if args.metric:
        return args.metric
    from explorer.data import default_metric
    metric = default_metric(args.data)
    if metric == "photometric":
        from explorer.console import err_console
        err_console.print(f"{args.data}: no depth in its validation frames: each path is scored by its photometric "
                          "error, warping the neighbouring frames with the motion the LiDAR measures (--metric)")
    return metric


def _time_limits(args, started: float):
    """(sampling timeout in seconds or None, the whole run's TimeLimit or None)."""
    from explorer.study.planning import TimeLimit
    if (args.time_limit or 0) < 0 or (args.timeout or 0) < 0:
        raise UserError("--time-limit and --timeout must be 0 (none) or more, e.g. 15m")
    # a sampling time the user asks for is not cut short by the default limit
    time_limit = args.time_limit if args.time_limit is not None else (960.0 if args.timeout is None else 0.0)
    timeout = 180.0 if args.timeout is None else (None if args.timeout == 0 else args.timeout)
    limit = None
    if time_limit:
        # what the user did not fix, the plan may shrink to fit the limit
        free = {k for k in ("supernet_steps", "finalists", "finalist_steps") if getattr(args, k) is None}
        limit = TimeLimit(time_limit, started, frozenset(free))
    return timeout, limit


def _baselines(args) -> tuple[str, ...]:
    from explorer.study.config import DEFAULT_BASELINES
    if args.no_baselines:
        if args.baselines:
            raise UserError("give --baselines NAMES or --no-baselines, not both")
        return ()
    if args.baselines is None:
        return DEFAULT_BASELINES
    names = tuple(n.strip() for n in args.baselines.split(",") if n.strip())
    if not names:
        raise UserError("--baselines needs at least one name (or use --no-baselines)")
    return names


def _print_retries(outcome, cfg) -> None:
    from explorer.console import err_console
    from explorer.study import trial_record
    from explorer.study.results import baseline_label
    trials = {t.number: t for t in outcome.study.get_trials(deepcopy=False)}
    def what(n: int) -> str:
        b = trial_record(trials[n]).baseline if n in trials else None
        return f"trial {n}" + (f" ({baseline_label(b)})" if b else "")
    for old, new in outcome.retried.items():
        err_console.print(f"{what(old)} was interrupted: tried again as trial {new}")
    for old in outcome.not_retried:
        err_console.print(f"{what(old)} was interrupted and is not tried again (--max-retries {cfg.max_retries} "
                          "reached)")


def _print_missing_baselines(view, has_winner: bool) -> None:
    """A missing comparison is said, with why, never dropped silently."""
    from explorer.console import console
    from explorer.study.results import missing_baselines
    missing = missing_baselines(view)
    if missing and all("--no-baselines" in m["why"] for m in missing):
        console.print("no baselines (the study was created with --no-baselines): no ratio to the paper design")
        return
    for m in missing:
        lead = "no ratio to the paper-design baseline:" if m["name"] == "paper" and has_winner \
            else f"baseline {m['label']} missing:"
        console.print(f"{lead} {m['why']}", markup=False, highlight=False)


def _print_outcome(view, cfg, storage_url: str, reports: Path, write_report: bool) -> None:
    """The search's closing summary of the study ``view`` reads (explorer.study.view), ``cfg`` its settings
    as this run ran them (a time limit may have sized its finalists); with ``write_report``, its report."""
    import optuna
    from explorer.console import console, print_frame
    from explorer.study.results import (baseline_label, baseline_trial, best_trial, estimate_fidelity,
                                        figures_source, finalists_agreement, finalists_frame, is_retrained,
                                        path_table, unbeaten_baseline, wall_time, winner)
    from explorer.space import Candidate
    from explorer.study import trial_record
    from explorer.study.envelope import envelope_summary
    study = view.study
    states = [t.state for t in view.trials]
    count = {s.name.lower(): states.count(s) for s in optuna.trial.TrialState if states.count(s)}
    console.print(f"study [bold]{cfg.study}[/bold]: " + ", ".join(f"{v} {k}" for k, v in count.items()))
    best, estimate = winner(study), best_trial(study)
    if best is None:
        console.print("no candidate trial completed yet: run longer (--timeout / --trials)")
    else:
        retrained = is_retrained(best)
        rec = trial_record(best)
        cand = Candidate.from_dict(rec.shipped_candidate)
        how = "retrained" if retrained else f"estimated ({rec.evaluator_name})"
        unbeaten = unbeaten_baseline(study)
        lead = "best searched candidate" if unbeaten is not None else "winner"
        console.print(f"{lead}: trial {best.number} ({rec.candidate_key}) anytime loss [bold]{best.values[0]:.4f}"
                      f"[/bold] {how}, for {cfg.budgets[0]} on {cfg.device}")
        console.print(f"  {cand.describe()}")
        _print_shipping(rec)
        print_frame(path_table(best, [view.context.device]), f"{lead}, per path")
        console.print(f"  {figures_source(best, cfg.train_size)}", markup=False, highlight=False)
        fin = finalists_frame(study)
        if not fin.empty:
            cols = ["model", "candidate_key", "estimated", "retrained", "estimated_rank", "retrained_rank"]
            print_frame(fin[cols], f"finalists: search estimate vs retrained ({cfg.finalist_steps} steps)")
            agreement = finalists_agreement(study)
            if agreement:
                console.print(f"finalists' agreement: Kendall tau {agreement['tau']:.2f} over {agreement['rows']} "
                              "rows the estimate itself chose (no measure of how it ranks the rest of the space)")
        fidelity = estimate_fidelity(view)
        if fidelity:
            console.print(f"estimate fidelity: {fidelity}", markup=False, highlight=False)
        paper = baseline_trial(study, "paper", retrained=retrained)
        if paper is not None:
            kind = "retrained " if retrained else ""
            once = f" (one training run of each, seed {cfg.seed})" if retrained else ""
            console.print(f"ratio to the {kind}paper-design baseline ({paper.values[0]:.4f}): "
                          f"[bold]{best.values[0] / paper.values[0]:.3f}[/bold]{once}")
        about_envelope = envelope_summary(view, storage_url, reports)
        if about_envelope:
            console.print(about_envelope, markup=False, highlight=False)
        if retrained and estimate is not None and estimate.number != rec.finalist.estimate_trial:
            console.print(f"  (the search's best estimate was trial {estimate.number}; retraining ranked another first)")
        if unbeaten is not None:   # said plainly: the study's best model is then a baseline, not a candidate
            console.print(f"[bold]no searched candidate beat the {baseline_label(trial_record(unbeaten).baseline)} "
                          f"after retraining[/bold] ({best.values[0]:.4f} against {unbeaten.values[0]:.4f}): the best "
                          "model this study found is that baseline; give the search more time (--time-limit) or more "
                          "finalists (--finalists)")
    _print_missing_baselines(view, best is not None)
    console.print(f"wall time: {wall_time(view)}", markup=False, highlight=False)
    from explorer.study.storage import redacted
    console.print(f"study: {redacted(storage_url)}", markup=False, highlight=False)
    if write_report:
        try:
            from explorer.report import write_report as _write
        except ImportError:
            return
        from explorer.errors import kept_if_refused
        with kept_if_refused(lambda: f"the search is done and its study stored in {redacted(storage_url)}: `explorer "
                             f"report --study {cfg.study}` writes the report"):
            path = _write(view, out_dir=reports / cfg.study, storage_url=storage_url)
        console.print(f"report: {path}")


def _print_shipping(rec) -> None:
    """What the winner's record ``rec`` says of the network that ships: each exit left out, and a last
    path that a halt after it never returns."""
    from explorer.console import console
    from explorer.model.shipped import DroppedExit, last_path_note
    for dropped in (rec.shipped.dropped if rec.shipped is not None else []):
        console.print(f"  {DroppedExit.from_dict(dropped).describe(rec.error_metric)}: left out of what ships "
                      "(--keep-every-exit keeps it)", markup=False, highlight=False)
    note = last_path_note(rec.losses_of(), rec.error_metric)
    if note:
        console.print(f"  {note}", markup=False, highlight=False)


def cmd_rescore(args) -> None:
    from explorer.cli._rescore import print_rescored
    from explorer.console import print_json
    from explorer.study.results import rescore
    from explorer.study.storage import load_study
    from explorer.study.view import study_view
    # its stored settings, space and profile read first: a damaged one is one line
    view = study_view(load_study(args.study, args.storage, Path(args.reports)))
    frame = rescore(view.study, args.device, args.budget, args.metric)
    if frame.empty:
        raise UserError(f"study '{args.study}' has no completed trial to re-score yet")
    if args.csv:
        write_output(args.csv, frame.to_csv(index=False))
    if args.json:
        print_json(frame.to_dict("records"))
    else:   # measured and estimated apart, and which to trust
        print_rescored(view, frame, args)


def cmd_envelope(args) -> None:
    import pandas as pd

    from explorer.console import console, print_frame, print_json, progress
    from explorer.report import write_report
    from explorer.study.envelope import envelope, train_envelope
    from explorer.study.storage import load_study, local_url, searching_alone
    from explorer.study.view import study_view
    if args.networks < 1:
        raise UserError("--networks must be at least 1")
    study = load_study(args.study, args.storage, Path(args.reports))
    view = study_view(study)   # a damaged stored space or profile is one line before any work
    config = view.config
    deadline = time.time() + args.time_limit if args.time_limit else None
    train_on_free_cores()
    url = args.storage or local_url(args.study, Path(args.reports))
    with searching_alone(url, args.study), progress(transient=True) as bar:   # one search or envelope at a time
        task = bar.add_task("dedicated networks", total=None, status="")
        train_envelope(view, args.networks, Path(args.reports), deadline,
                       progress=lambda i, n, what: bar.update(task, completed=i, total=n, status=what))
    view = study_view(study)   # with the networks just retrained
    found = envelope(view)
    if found is None:
        raise UserError(f"study '{args.study}' has no retrained winner or no dedicated network to compare: run "
                        "the search with finalists, and give the envelope time (--time-limit)")
    if args.json:
        print_json({"loss": found.loss, "winner_loss": found.winner_loss, "ratio": found.ratio,
                    "costs": found.costs, "errors": found.errors, "networks": found.networks})
        return
    print_frame(pd.DataFrame(found.networks), "dedicated networks (each trained for one path), retrained and "
                f"measured at {'x'.join(map(str, config.input_size))}, costed on {config.device}")
    line = f"envelope of dedicated networks: anytime loss {found.loss:.4f} for {config.budgets[0]} on {config.device}"
    if found.ratio is not None:
        line += f"; the winner {found.winner_loss:.4f}, [bold]{found.ratio:.3f}[/bold] x the envelope"
    console.print(line)
    if args.report:   # the report draws the envelope under the winner's curve: bring it up to date
        path = write_report(view, out_dir=Path(args.reports) / config.study, storage_url=args.storage)
        console.print(f"report: {path}")


def cmd_report(args) -> None:
    from explorer.console import console
    from explorer.report import write_report
    from explorer.study.storage import load_study
    from explorer.files import check_writable_folder
    from explorer.study.view import study_view
    # its stored settings, space and profile read first: a damaged one is one line, nothing written
    view = study_view(load_study(args.study, args.storage, Path(args.reports)))
    out = Path(args.out) if args.out else Path(args.reports) / args.study
    check_writable_folder(out, "report", "give --out a folder you can write")
    path = write_report(view, out_dir=out, devices=args.device, budgets=args.budget, data=args.data,
                        curve=Path(args.curve) if args.curve else None, storage_url=args.storage)
    console.print(f"report: {path}")


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    _register_search(add, reports)

    s = add("envelope", cmd_envelope, "the envelope of dedicated networks (each trained for one path): how close "
            "the winner comes to the best network for each deadline known in advance")
    s.add_argument("--study", required=True)
    s.add_argument("--storage")
    s.add_argument("--networks", type=int, default=4, help="dedicated networks spread over the budget's range, "
                   "chosen from the search's estimates and retrained with the finalists' recipe (default 4; those "
                   "already retrained are kept, a killed run resumes)")
    s.add_argument("--time-limit", type=_duration_s, default=None, help="start no network that would end after "
                   "this long (default: none)")
    s.add_argument("--no-report", dest="report", action="store_false", help="leave the study's HTML report as it "
                   "is (by default it is written again, with the envelope)")
    s.add_argument("--json", action="store_true")
    s.add_argument("--reports", **reports)

    s = add("rescore", cmd_rescore, "rank a finished study's trials for another device or budget")
    s.add_argument("--study", required=True)
    s.add_argument("--storage")
    s.add_argument("--device", required=True, help="device profile to re-score for: a built-in name (see "
                   "explorer devices) or a YAML file from explorer calibrate")
    s.add_argument("--budget", action="append", required=True, help="budget distribution, e.g. time:uniform:100ms; "
                   "repeatable, the table is sorted by the first")
    s.add_argument("--metric", default="rmse", choices=["rmse", "mae", "rel"])
    s.add_argument("--top", type=int, default=15)
    s.add_argument("--csv", help="also write the whole table to this CSV file (default: none)")
    s.add_argument("--json", action="store_true")
    s.add_argument("--reports", **reports)

    s = add("report", cmd_report, "write a study's self-contained HTML report")
    s.add_argument("--study", required=True)
    s.add_argument("--storage")
    s.add_argument("--device", action="append", help="devices for the tables (default: the study's)")
    s.add_argument("--budget", action="append", help="budgets for the tables (default: a standard set)")
    s.add_argument("--data", help="data set for the depth-map figure (default: the study's)")
    s.add_argument("--out", help="folder to write report.html and its figures into (default REPORTS/STUDY/, "
                   "next to the study)")
    s.add_argument("--curve", help="anytime_curve.json from explorer curve (default: OUT/export/ if there)")
    s.add_argument("--reports", **reports)


def _register_search(add, reports: dict) -> None:
    s = add("search", cmd_search, "search the space for the lowest anytime loss on a device")
    s.add_argument("--device", help="profile name or YAML (default tx2)")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--budget", action="append", help="repeatable; the first is the objective "
                   "(default time:uniform:33ms)")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--lidar")
    s.add_argument("--study", help="study name (default DEVICE-SPACE); the same name resumes")
    s.add_argument("--storage", help="Optuna storage URL (default: the journal file "
                   "reports/<study>/journal.log; postgresql://... for several machines)")
    s.add_argument("--workers", type=_bounded_int(1, MAX_WORKERS, "processes on this machine"), default=1, help="processes on this machine: sampling (journal storage) "
                   "and the finalists retrained at once on a CPU (with GPUs: one finalist per GPU at once)")
    s.add_argument("--time-limit", type=_duration_s, default=None, help="wall clock for the whole run: data, "
                   "supernet training, sampling, finalists (default 16m, none when --timeout is given; 0 = none). "
                   "The machine is measured first (seconds); sampling, the finalists' steps (to 2/3), the supernet's "
                   "steps, then the finalists shrink to fit where not given, and the plan is printed; the time "
                   "the finalists leave goes to the envelope's dedicated networks (see explorer envelope)")
    s.add_argument("--timeout", type=_duration_s, default=None, help="stop sampling after this long (default 3m: "
                   "hundreds to over a thousand supernet estimates on a 2-core CPU, by its speed; 0 = none)")
    s.add_argument("--trials", type=int, default=None, help="stop after this many finished trials")
    s.add_argument("--objectives", default="anytime_loss", help="e.g. anytime_loss,params (NSGA-II)")
    s.add_argument("--metric", default=None, choices=["rmse", "mae", "rel", "photometric"],
                   help="how each path is scored: rmse (default where the validation frames have depth), mae, rel, "
                   "or photometric (the default on a recording without depth: the error of warping the neighbouring "
                   "frames with the camera's motion as the LiDAR measures it)")
    s.add_argument("--max-params", type=_count, help="reject candidates above this, e.g. 2.5M")
    s.add_argument("--max-first-exit", type=_ms, help="reject candidates whose first exit is later, e.g. 10ms")
    s.add_argument("--evaluator", default="auto", choices=["auto", "supernet", "proxy"],
                   help="how a candidate's accuracy is estimated: its slice of the space's supernet (trained "
                   "once, then under a second a candidate) or proxy training alone (~20 s a candidate). "
                   "auto (default): supernet with dense labels, proxy with --supervision self/mixed")
    s.add_argument("--sampler", default="tpe", choices=["tpe", "random"],
                   help="how candidates are proposed: tpe (default; Optuna's TPE over the trials so far, NSGA-II "
                   "with several --objectives) or random (uniformly, each trial independent of the others)")
    s.add_argument("--supernet", help="supernet file (default: the one cached for space, data and recipe, "
                   "trained first if missing)")
    s.add_argument("--supernet-steps", type=int, default=None, help="supernet training steps (default: what "
                   "--time-limit leaves, 300-600, else 600; a resumed study keeps its own)")
    s.add_argument("--finalists", type=int, default=None, help="best candidates (one per image encoder first) "
                   "retrained stand-alone at the end, next to the baselines (default 3, fewer if --time-limit needs; 0 = none)")
    s.add_argument("--finalist-steps", type=int, default=None, help="steps of the finalists' longer recipe "
                   "(default 300, down to 150 if --time-limit needs), at --train-size")
    s.add_argument("--tune-steps", type=int, help="steps the finalists and baselines then train at "
                   "--input-size, where every path of theirs is measured (default: a fifteenth of --finalist-steps, "
                   "at least 20, so 20 for the default 300; 0 = none: measured there as trained; none when the two "
                   "sizes are equal)")
    s.add_argument("--proxy-steps", type=int, default=150, help="training steps of each candidate the proxy "
                   "evaluator trains (default 150)")
    deprecated_alias(s, "--train-steps", "--proxy-steps")
    s.add_argument("--train-size", type=_size, default=(64, 64), help="training resolution HxW of the proxy "
                   "candidates, the supernet and the finalists' first steps (default 64x64): the search's estimates "
                   "are made at this size")
    s.add_argument("--batch-size", type=int, default=16)
    s.add_argument("--amp", action="store_true", help="bf16 autocast of the supernet's forward passes: for a GPU "
                   "(with --train-size 224x224 --batch-size 64, the GPU recipe of `explorer supernet train`); "
                   "slower on a CPU")
    s.add_argument("--head-kinds", choices=HEAD_KINDS, default="rotate", help="which of the supernet's subnets "
                   "trains which kind of exit head: rotate (default; every kind on every kind of backbone), cover, "
                   "random (as supernets made before rotate); part of the study's identity")
    s.add_argument("--input-size", type=_size, default=(224, 224),
                   help="deployment resolution HxW, at which paths are costed and the finalists and baselines "
                   "tuned and measured (default 224x224)")
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--baselines", default=None, metavar="NAMES",
                   help="what the study compares against, comma-separated: paper, paper-nee, fastdepth and the "
                   "reference networks of `explorer profile --help` (s2d-resnet18, monodepth2-resnet18, ...), "
                   "which are retrained with the finalists' recipe (default paper,paper-nee,fastdepth)")
    s.add_argument("--no-baselines", action="store_true", help="compare against nothing (no ratio to the paper design)")
    s.add_argument("--max-retries", type=int, default=2, help="try an interrupted trial (killed, Ctrl-C, "
                   "lost worker) again at most this many times (default 2); a trial that fails is not")
    s.add_argument("--no-pruning", action="store_true")
    s.add_argument("--keep-every-exit", action="store_true")
    s.add_argument("--no-weights", action="store_true", help="do not keep trained weights as artifacts")
    s.add_argument("--no-report", dest="report", action="store_false", help="skip the HTML report")
    _add_supervision(s)
    s.add_argument("--reports", **reports)
