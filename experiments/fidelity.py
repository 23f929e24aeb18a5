"""How well does the search's estimate rank the space? The supernet's anytime loss against long
stand-alone trainings of the same candidates, and its variants:

- ``fidelity``: the supernet of the search's recipe (or of changed recipes, compared) against the long
  labels, beside the proxy and the finalists' recipe;
- ``short_supernet``: a supernet stopped short of its recipe against a recipe as short, completed.

    python -m experiments.fidelity --only fidelity [its options]
    python -m experiments.fidelity --only short_supernet [--steps 140]

The long labels are cached (``experiments.lib.labels``); ``benchmarks/labels`` holds those made so far.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import torch

from explorer.space import SearchSpace
from explorer.study.config import SearchConfig
from explorer.supernet import SupernetRecipe, default_path, read_supernet, train_supernet

from benchmarks.harness import Bench, Case, ROOT, rotated, run_suite
from experiments.lib.fidelity import (CANDIDATE_SEED, estimate, estimates, fidelity_candidates, fine_tuned_estimate,
                                      label_jobs, label_recipes, LABEL_SEEDS, labels_of, rank_figures,
                                      run_label_jobs, supernet_evaluator)
from experiments.lib.labels import BUDGET, cached
from experiments.lib.per_exit import exact_at_taus, last_exit_taus, path_taus
from experiments.lib.predictor import held_out_taus

FIGURES = {"tau": ("Kendall tau", "higher"), "spearman": ("Spearman", "higher"),
           "recall": ("top-5 recall in the best 10", "higher")}


def parse_recipe(text: str, base: SupernetRecipe) -> SupernetRecipe:
    """``base`` with the ``key=value,...`` of --supernet-recipe (values typed as the field's default)."""
    changes = {}
    for pair in filter(None, text.split(",")):
        key, _, value = pair.partition("=")
        default = getattr(base, key)
        changes[key] = value if isinstance(default, str) else type(default)(float(value))
    return dataclasses.replace(base, **changes)


def supernet_files(files: list, recipe_text: str, seeds: str, space: SearchSpace, config: SearchConfig
                   ) -> list[tuple[str, Path]]:
    """(name, file) of the supernets to score: the given ``files``, else the search's recipe changed by
    ``recipe_text`` at each of ``seeds`` (found in the search's cache, trained there if missing)."""
    if files:
        return [(Path(f).stem, Path(f)) for f in files]
    out = []
    for seed in [int(s) for s in seeds.split(",") if s]:
        rec = parse_recipe(recipe_text, dataclasses.replace(config.supernet_recipe(), seed=seed))
        file = default_path(space, config.data, rec)
        if not file.is_file() or not read_supernet(file).get("complete"):
            print(f"training the supernet {rec.to_dict()} into {file}", flush=True)
        train_supernet(space, config.data, rec, file)
        out.append((f"seed{seed}", file))
    return out


def label_table(cands, seeds) -> tuple[list, dict, dict]:
    """(the candidates with long labels, their labels {candidate: {recipe: mean over the seeds}} for the
    recipes they have, their long labels per seed {candidate: [...]})."""
    rows = {c: {name: labels_of(c, name, seeds) for name in label_recipes()} for c in cands}
    labelled = [c for c in cands if rows[c]["long"]]
    return labelled, {c: {name: statistics.mean(v) for name, v in rows[c].items() if v} for c in labelled}, \
        {c: rows[c]["long"] for c in labelled}


def _add_ranks(bench: Bench, prefix: str, what: str, estimates: dict, table: dict) -> dict | None:
    """Kendall tau, Spearman and top-5 recall of ``estimates`` {candidate: value} against the long labels
    (None under 3 candidates: no rank figure means anything there)."""
    if len(estimates) < 3:
        return None
    figs = rank_figures(list(estimates.values()), [table[c]["long"] for c in estimates])
    for k, (label, better) in FIGURES.items():
        if k in figs:
            bench.add(bench.figure(f"{k}_{prefix}", f"{what}: {label} against the long labels", "", better), figs[k])
    return figs


def label_figures(bench: Bench, labelled: list, table: dict, per_seed: dict) -> None:
    """The labels' seed spread and the proxy's and finalists' recipes' fidelity (one value each)."""
    both = [c for c in labelled if len(per_seed[c]) >= 2]
    if len(both) >= 3:
        spread = rank_figures([per_seed[c][0] for c in both], [per_seed[c][1] for c in both])
        bench.add(bench.figure("labels_seed_tau", "long labels: Kendall tau between seeds 0 and 1", "", "higher"),
                  spread["tau"])
        gaps = [abs(per_seed[c][0] - per_seed[c][1]) for c in both]
        means = sorted(table[c]["long"] for c in labelled)
        bench.note(f"long labels' seed-to-seed Kendall tau {spread['tau']:.3f} over {len(both)} candidates "
                   f"(Spearman {spread['spearman']:.3f}); median seed-to-seed difference "
                   f"{statistics.median(gaps):.4f}, "
                   f"against labels spanning {means[0]:.4f}-{means[-1]:.4f}")
    for name in ("proxy", "finalist"):
        have = {c: table[c][name] for c in labelled if name in table[c]}
        if _add_ranks(bench, name, f"{name} recipe", have, table):
            bench.note(f"{name} recipe ranked over {len(have)} candidates")


def score_supernet(bench: Bench, prefix: str, est: dict, table: dict, what: str = "") -> None:
    """The rank figures (``*_{prefix}``) of one supernet's estimates over the labelled candidates,
    labelled ``what`` (default: the prefix)."""
    est = {c: v for c, v in est.items() if c in table}
    what = what or prefix.replace("_", " ")
    _add_ranks(bench, prefix, what, est, table)
    retrained = [c for c in est if "finalist" in table[c]]
    if len(retrained) >= 3:   # against what a search's report shows beside an estimate: the retrained figure
        bench.add(bench.figure(f"tau_{prefix}_vs_finalist", f"{what}: Kendall tau against the finalists' recipe",
                               "", None),
                  rank_figures([est[c] for c in retrained], [table[c]["finalist"] for c in retrained])["tau"])
        bench.add(bench.figure(f"gap_{prefix}", f"{what}: median |estimate - finalists' recipe| (anytime loss)",
                               "", "lower"), statistics.median(abs(est[c] - table[c]["finalist"]) for c in retrained))
    for kind in (False, True):   # plain and residual heads, where the estimate was seen to part
        sub = [c for c in est if c.exit_residual == kind]
        if len(sub) >= 4:
            t = rank_figures([est[c] for c in sub], [table[c]["long"] for c in sub])["tau"]
            head = "residual" if kind else "plain"
            bench.add(bench.figure(f"tau_{prefix}_{head}", f"{what}: Kendall tau over {head}-head "
                                   "candidates", "", "higher"), t)


def print_rows(est: dict, table: dict) -> None:
    for c in sorted((c for c in est if c in table), key=lambda c: table[c]["long"]):
        others = " ".join(f"{k} {table[c][k]:.4f}" for k in ("finalist", "proxy") if k in table[c])
        print(f"  {c.key} long {table[c]['long']:.4f} {others} supernet {est[c]:.4f}  {c.describe()[:80]}", flush=True)


def score_all(bench: Bench, args, space: SearchSpace, config: SearchConfig, cands: list, table: dict) -> list:
    """One repetition per supernet (the scored ones, then the --compare ones); the scored ones' recipes.
    Estimates are cached (_fidelity.estimates): every candidate is estimated, the labelled ones ranked."""
    items = [(name, file, "supernet") for name, file in
             supernet_files(args.supernet, args.supernet_recipe, args.supernet_seeds, space, config)]
    if args.compare or args.compare_recipe:
        items += [(name, file, "compared") for name, file in
                  supernet_files(args.compare, args.compare_recipe, args.compare_seeds, space, config)]
    sweep = [int(n) for n in args.calibration_sweep.split(",") if n]
    recipes, scored = [], []
    for rep in bench.repetitions(len(items)):
        name, file, prefix = items[rep]
        state = read_supernet(file)
        if prefix == "supernet":
            recipes.append(SupernetRecipe.from_dict(state["recipe"]))
        bench.note(f"{prefix} {name}: {state['step']} steps, recipe {state['recipe']}, trained in "
                   f"{state['seconds'] / 60:.1f} min; BatchNorm recalibrated on {args.calibration_images} frames")
        est = estimates(file, cands, space, args.calibration_images, config)
        # a compared supernet's figures say what it changes, so that a reader of the record need not
        # look for it in the command
        changes = args.compare_recipe if prefix == "compared" and not args.compare else ""
        score_supernet(bench, prefix, est, table, f"compared ({changes})" if changes else "")
        print_rows(est, table)
        if prefix != "supernet":
            continue
        scored.append(est)
        for n in sweep:
            _add_ranks(bench, f"calib{n}", f"supernet, BatchNorm recalibrated on {n} frames",
                       {c: v for c, v in estimates(file, cands, space, n, config).items() if c in table}, table)
        if args.fine_tune_steps:   # every slice trained a few steps alone, as a search could its top estimates
            evaluator = supernet_evaluator(file, space, config, calibration_images=args.calibration_images)
            tuned = {c: fine_tuned_estimate(evaluator, c, args.fine_tune_steps, lr_scale=args.fine_tune_lr)
                     for c in est if c in table}
            _add_ranks(bench, "fine_tuned", f"supernet slices fine-tuned {args.fine_tune_steps} steps "
                       f"at {args.fine_tune_lr:g}x the learning rate", tuned, table)
        if args.predictor or args.per_exit:   # both read the supernet's error at every path
            evaluator = supernet_evaluator(file, space, config, calibration_images=args.calibration_images)
            per_path = {c: [float(x) for x in evaluator(c).metrics["rmse"]] for c in est if c in table}
        if args.predictor:
            predictor_figures(bench, per_path, table)
        if args.per_exit:
            per_exit_figures(bench, per_path, name)
    supernets_agreement(bench, scored, table)
    return recipes


def predictor_figures(bench: Bench, per_path: dict, table: dict) -> None:
    """Kendall tau of the supernet's estimate corrected by an accuracy predictor (experiments.lib.predictor)
    fitted on other candidates' finalist-recipe results: 6 of them (what one earlier study retrains: 3
    finalists, 3 baselines; median of 20 draws) and all the others."""
    retrained = finalist_errors(per_path)
    estimated = {c: per_path[c] for c in retrained}
    labels = {c: table[c]["long"] for c in retrained}
    for count, name, what in ((6, "predictor6", "6 other candidates' (one earlier study's)"),
                              (len(labels) - 1, "predictor_all", "all the other candidates'")):
        bench.add(bench.figure(f"tau_{name}", f"supernet corrected by a predictor fitted on {what} finalists' "
                               "recipe results: Kendall tau against the long labels", "", "higher"),
                  statistics.median(held_out_taus(estimated, retrained, labels, count)))


def long_errors(cands) -> dict:
    """{candidate: the long labels' error at every path (mean over the label seeds)}."""
    long = label_recipes()["long"]
    labels = {}
    for c in cands:
        entries = [e for e in (cached(c, dataclasses.replace(long, seed=s)) for s in LABEL_SEEDS) if e]
        labels[c] = [statistics.mean(v) for v in zip(*(e["rmse"] for e in entries))]
    return labels


def finalist_errors(cands) -> dict:
    """{candidate: its error at every path trained alone with the finalists' recipe (first label seed)},
    for the candidates that have it."""
    finalist = dataclasses.replace(label_recipes()["finalist"], seed=LABEL_SEEDS[0])
    return {c: entry["rmse"] for c in cands if (entry := cached(c, finalist))}


def add_last_exit_figures(bench: Bench, prefix: str, what: str, estimated: dict, labels: dict) -> None:
    """Kendall tau of the last decoder exit's error within each head kind (``tau_{prefix}_last_{kind}``)."""
    for kind, tau in last_exit_taus(estimated, labels).items():
        bench.add(bench.figure(f"tau_{prefix}_last_{kind}", f"{what}: Kendall tau of the last exit's error over "
                               f"{kind}-head candidates", "", "higher"), tau)


def finalist_per_exit_figures(bench: Bench, labelled: list) -> None:
    """The finalists' recipe (every candidate trained alone) ordering the last exit's error within each head
    kind: the supernet's own figure read beside it says whether weight sharing loses what training alone
    keeps."""
    errors = finalist_errors(labelled)
    add_last_exit_figures(bench, "finalist", "finalist recipe", errors, long_errors(errors))


def per_exit_figures(bench: Bench, estimated: dict, name: str) -> None:
    """Per kind of path (experiments.lib.per_exit): the supernet's Kendall tau of that path's error over the
    candidates with it, and of the anytime loss were the supernet exact at that path alone. ``estimated``:
    {candidate: the supernet's error at every path}."""
    labels = long_errors(estimated)
    add_last_exit_figures(bench, "supernet", "supernet", estimated, labels)
    for kind, tau in exact_at_taus(estimated, labels).items():
        what = "the supernet as it is" if kind == "none" else f"the supernet exact at path {kind}"
        bench.add(bench.figure(f"tau_exact_{kind}", f"{what}: Kendall tau against the long labels", "", None), tau)
    for kind, (tau, gap, count) in path_taus(estimated, labels).items():
        bench.add(bench.figure(f"tau_path_{kind}", f"path {kind}: Kendall tau of its error over the candidates "
                               "with it", "", None), tau)
        bench.add(bench.figure(f"gap_path_{kind}", f"path {kind}: mean overestimate of its error", "", None), gap)
        bench.note(f"{name}: path {kind} on {count} candidates, Kendall tau {tau:.3f}, mean overestimate {gap:+.4f}")


def supernets_agreement(bench: Bench, scored: list[dict], table: dict) -> None:
    """Kendall tau between the first two scored supernets' estimates: where they agree far better with
    each other than with the labels, the estimate's error is the weight sharing's bias, which another
    seed or more supernets averaged do not remove, rather than noise."""
    if len(scored) < 2:
        return
    both = [c for c in scored[0] if c in scored[1] and c in table]
    if len(both) >= 3:
        tau = rank_figures([scored[0][c] for c in both], [scored[1][c] for c in both])["tau"]
        bench.add(bench.figure("supernets_tau", "supernet: Kendall tau between the first two supernets' estimates",
                               "", None), tau)


def bench_fidelity(argv: Sequence[str] | None = None) -> None:
    """Rank fidelity of the search's estimate on the default space: how well the supernet's anytime loss
    (tx2, U(0, 33 ms), as the search ranks) orders random candidates and the baselines against the same
    candidates trained alone with a recipe 4x longer than the finalists' (mean of 2 seeds), beside the
    proxy (the search's 150-step recipe) and the finalists' recipe. Kendall tau, Spearman and top-5
    recall (how many of the long labels' best 5 are in the estimate's best 10); the labels' own
    seed-to-seed tau bounds any of them.

        python -m experiments.fidelity [--candidates 24] [--supernet-seeds 0,1] [--supernet FILE ...]
            [--supernet-recipe K=V,...] [--compare-recipe head_kinds=cover] [--calibration-sweep 64,1024]
            [--fine-tune-steps 30] [--predictor] [--per-exit] [--store]
        python -m experiments.fidelity --labels-only --worker 0   # fill the label cache (several workers may)

    Each repetition is one supernet: trained here with each of --supernet-seeds (the search's recipe, cached
    beside the search's own supernets), or read from each --supernet file. The stand-alone labels are trained
    once and cached (experiments.lib.labels), so re-scoring a new supernet takes minutes. The label figures
    (seed spread, proxy, finalists' recipe) do not depend on the supernet and have one value. --store writes
    the supernets' figures into explorer/supernet/fidelity.json (package data), which a search's summary and
    report quote for studies of the same space, data and supernet recipe.
    """
    bench = Bench("bench_fidelity", "Supernet rank fidelity on the default space against long stand-alone labels",
                  bench_fidelity.__doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=24, help="random default-space candidates (plus the baselines)")
    ap.add_argument("--supernet", action="append", default=[], help="score this supernet file (repeatable); "
                    "default: train one per --supernet-seeds")
    ap.add_argument("--supernet-seeds", default="0,1", help="seeds of the supernets trained and scored")
    ap.add_argument("--supernet-recipe", default="", help="changes to the search's supernet recipe, key=value,...")
    ap.add_argument("--calibration-images", type=int, default=256, help="BatchNorm recalibration frames")
    ap.add_argument("--compare", action="append", default=[], help="also score this supernet file (figures "
                    "*_compared; repeatable), e.g. one of an earlier recipe")
    ap.add_argument("--compare-recipe", default="", help="also score supernets of the search's recipe with these "
                    "changes, key=value,... (figures *_compared), one per --compare-seeds")
    ap.add_argument("--compare-seeds", default="0,1", help="seeds of the --compare-recipe supernets")
    ap.add_argument("--calibration-sweep", default="", help="also the scored supernets' figures with these "
                    "BatchNorm recalibration frame counts, e.g. 64,1024")
    ap.add_argument("--fine-tune-steps", type=int, default=0, help="also rank every candidate's slice after "
                    "this many steps of stand-alone training (0: not)")
    ap.add_argument("--fine-tune-lr", type=float, default=0.1, help="with --fine-tune-steps: the fine-tuning's "
                    "learning rate as a fraction of the search's (default 0.1)")
    ap.add_argument("--predictor", action="store_true", help="also rank the supernet's estimate corrected by an "
                    "accuracy predictor fitted on other candidates' finalists' recipe results (held out)")
    ap.add_argument("--per-exit", action="store_true", help="also, per kind of path, the supernet's rank figures "
                    "of its error and of the anytime loss were the supernet exact there (where the ranking is lost)")
    ap.add_argument("--label-seeds", default=",".join(map(str, LABEL_SEEDS)), help="seeds of the stand-alone labels")
    ap.add_argument("--cached-labels", action="store_true", help="score with the labels already cached, train none")
    ap.add_argument("--store", action="store_true", help="store the supernets' figures as the package's "
                    "fidelity record of their space, data and recipe")
    ap.add_argument("--labels-only", action="store_true", help="only train the labels not cached yet")
    ap.add_argument("--worker", type=int, default=0, help="with --labels-only: this worker's number (for its log)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (default: 1 with --labels-only, so "
                    "that workers share the cores, else 2)")
    args = bench.parse_args(ap, argv)
    space = SearchSpace.from_yaml("anytime_depth")
    config = SearchConfig(study="fidelity")
    cands = fidelity_candidates(space, args.candidates)
    seeds = tuple(int(s) for s in args.label_seeds.split(","))
    if not args.cached_labels:
        torch.set_num_threads(args.threads or (1 if args.labels_only else 2))
        run_label_jobs(label_jobs(cands, seeds), args.worker)
    if args.labels_only:
        return
    torch.set_num_threads(args.threads or 2)
    labelled, table, per_seed = label_table(cands, seeds)
    rec = label_recipes(config)
    bench.note(f"{len(labelled)} of {len(cands)} candidates with long labels ({args.candidates} random, drawn "
               f"with seed {CANDIDATE_SEED}, and the baselines); long labels {rec['long'].steps} steps (mean of "
               f"seeds {args.label_seeds}), finalists' {rec['finalist'].steps}, proxy {rec['proxy'].steps}, batch "
               f"{rec['long'].batch_size} at {rec['long'].input_size[0]}x{rec['long'].input_size[1]}; anytime loss "
               f"on tx2, {BUDGET}")
    label_figures(bench, labelled, table, per_seed)
    if args.per_exit:
        finalist_per_exit_figures(bench, labelled)
    recipes = score_all(bench, args, space, config, cands, table)
    path = bench.finish()
    if args.store:
        store(bench, space, config, recipes, labelled, rec["long"].steps, seeds, path)


def store(bench: Bench, space: SearchSpace, config: SearchConfig, recipes: list, labelled: list, label_steps: int,
          seeds: tuple, record: Path | None) -> None:
    """The supernets' figures as the package's fidelity record of their (space, data, recipe)."""
    from explorer.study.config import BASELINES
    from explorer.supernet import store_fidelity
    if len({json.dumps({k: v for k, v in r.identity().items() if k != "seed"}, sort_keys=True) for r in recipes}) != 1:
        sys.exit("--store: the supernets scored differ in more than their seed; store one recipe at a time")
    figs = {k: [round(v, 4) for v in bench.figures[f"{k}_supernet"].reps] for k in FIGURES
            if bench.figures.get(f"{k}_supernet")}
    spread = bench.figures.get("labels_seed_tau")
    finalist = bench.figures.get("tau_finalist")
    baselines = {make().key for make in BASELINES.values()}
    entry = {**figs, "candidates": sum(c.key not in baselines for c in labelled), "label_steps": label_steps,
             "label_seeds": list(seeds),
             "labels_seed_tau": round(spread.reps[0], 4) if spread and spread.reps else None,
             "finalist_tau": round(finalist.reps[0], 4) if finalist and finalist.reps else None,
             "supernet_seeds": [r.seed for r in recipes], "date": bench.started.strftime("%Y-%m-%d"),
             "record": str(record.relative_to(ROOT)) if record else None}
    store_fidelity(space, config.data, recipes[0], entry)
    print(f"stored in explorer/supernet/fidelity.json: {entry}")


# -- short_supernet --------------------------------------------------------------------------------

VARIANTS = ("stopped", "complete")

FIGURES = {"tau": ("Kendall tau", "higher"), "spearman": ("Spearman", "higher"),
           "recall": ("top-5 recall in the best 10", "higher")}

def train_variant(name: str, seed: int, args, space: SearchSpace, config: SearchConfig, folder: Path) -> Path:
    """The supernet of ``name`` for ``seed``: stopped after ``args.steps`` of ``args.recipe_steps``, or a
    recipe of ``args.steps`` trained to its end."""
    steps = args.recipe_steps if name == "stopped" else args.steps
    recipe = dataclasses.replace(config.supernet_recipe(), steps=steps, seed=seed)
    out = folder / f"{name}-{seed}.pt"
    t0 = time.perf_counter()
    train_supernet(space, config.data, recipe, out, torch.device("cpu"), stop_after_steps=args.steps)
    print(f"  {name} (seed {seed}): {args.steps} steps of a {steps}-step recipe in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    return out


def bench_short_supernet(argv: Sequence[str] | None = None) -> None:
    """When a time limit leaves a supernet only K steps: is it better stopped at step K of the usual
    recipe (what a search does when its deadline comes first: the learning rate still high and, before
    half the steps, the narrow widths never trained by progressive shrinking) or trained with a recipe of
    K steps that it completes (the same schedule, compressed)?

    Each repetition is one supernet seed: the search's recipe with ``--recipe-steps`` (default 300, the
    planner's minimum) stopped after ``--steps`` K (default 140, about what a 5-minute search fit on a
    2-core CPU), against the same recipe with K steps, trained to its end; the two are trained one after
    the other, their order turning from seed to seed. Each one's estimates of the stand-alone label set
    (bench_fidelity's random default-space candidates and the baselines) are ranked against the long
    labels (the finalists' recipe 4x longer, mean of 2 seeds): Kendall tau, Spearman, top-5 recall.

        ANYTIME_BENCH_CACHE=benchmarks/labels python -m experiments.fidelity --only short_supernet [--reps 3] [--steps 140]

    The labels must be in the cache (``benchmarks/labels`` holds them): nothing is trained for them here.
    """
    bench = Bench("bench_short_supernet", "a supernet stopped short of its recipe against a recipe as short, completed", bench_short_supernet.__doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=140, help="the steps each supernet trains (default 140)")
    ap.add_argument("--recipe-steps", type=int, default=300, help="the stopped supernet's recipe (default 300)")
    ap.add_argument("--candidates", type=int, default=24, help="random candidates of the label set (default 24)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = bench.parse_args(ap, argv)
    torch.set_num_threads(args.threads)
    space, config = SearchSpace.from_yaml("anytime_depth"), SearchConfig(study="short-supernet")
    candidates = [c for c in fidelity_candidates(space, args.candidates) if space.contains(c)]
    labels = {c: labels_of(c, "long") for c in candidates}
    candidates = [c for c in candidates if labels[c]]
    if len(candidates) < 10:
        raise SystemExit(f"{len(candidates)} candidates have long labels in the cache: point ANYTIME_BENCH_CACHE "
                         "at benchmarks/labels")
    long = [statistics.mean(labels[c]) for c in candidates]
    for name in VARIANTS:
        for key, (label, better) in FIGURES.items():
            bench.figure(f"{key}_{name}", f"{name}: {label} against the long labels", "", better)
    bench.figure("tau_gain", "complete minus stopped, Kendall tau in the same seed", "", "higher")
    with tempfile.TemporaryDirectory(prefix="bench-short-supernet-") as tmp:
        for seed in bench.repetitions():
            taus = {}
            for name in rotated(list(VARIANTS), seed):
                file = train_variant(name, seed, args, space, config, Path(tmp))
                evaluator = supernet_evaluator(file, space, config, require_complete=False)   # as a search reads it
                figures = rank_figures([estimate(evaluator, c) for c in candidates], long)
                del evaluator
                for key, value in figures.items():
                    bench.add(f"{key}_{name}", value)
                taus[name] = figures["tau"]
            bench.add("tau_gain", taus["complete"] - taus["stopped"])
    bench.note(f"cpu, torch threads {args.threads}; {args.steps} supernet steps; the stopped one's recipe "
               f"{args.recipe_steps} steps; {len(candidates)} candidates with long labels")
    bench.finish()


CASES = (Case(bench_fidelity), Case(bench_short_supernet))

if __name__ == "__main__":
    run_suite(CASES)
