"""``explorer rescore``'s tables: what was measured on retrained networks and what the search estimated,
in two tables that are never ranked together, then which to trust and how to measure an estimate."""

from __future__ import annotations

import pandas as pd

from explorer.anytime import parse_budget

#: the columns shown, by their short names: a table of a few budgets fits 80 columns without a cell
#: broken inside a word (the CSV and JSON keep the full names)
SHOWN = {"number": "trial", "model": "model", "first_exit_ms": "first ms", "last_exit_ms": "last ms",
         "params": "params"}


def budget_label(spec: str) -> str:
    """The paper's notation for a uniform budget (L_T@100ms, L_E@0.5J), the spec otherwise."""
    dist = parse_budget(spec)
    if dist.name == "uniform":
        return f"L_{'T' if dist.kind == 'time' else 'E'}@{dist.maximum:g}{dist.unit}"
    return dist.spec


def shown(frame: pd.DataFrame, budgets: list[str]) -> pd.DataFrame:
    """``frame`` (explorer.study.results.rescore) with short column names: the model is a baseline's
    name or the candidate's key, each budget its paper notation."""
    out = frame.assign(model=[b or k for b, k in zip(frame["baseline"], frame["candidate_key"])])
    columns = ["number", "model", *budgets, "first_exit_ms", "last_exit_ms", "params"]
    return out[columns].rename(columns={**SHOWN, **{b: budget_label(b) for b in budgets}})


def advice(study: str, frame: pd.DataFrame, budget: str, sizes: tuple[str, str], evaluator: str) -> str:
    """Which table to trust and, where the best estimate looks better than the best measurement, why it is
    not and how to measure it. ``sizes``: (deployment size, training size) as HxW."""
    deploy, train = sizes
    measured, estimates = frame[frame["figures"] == "measured"], frame[frame["figures"] != "measured"]
    if measured.empty:
        return (f"Nothing is measured yet: every figure is the search's estimate ({evaluator} at {train}), which "
                "ranks candidates among themselves only; the search's finalists (--finalists) retrain the best "
                f"and measure them at {deploy}.")
    best = measured.iloc[0]
    which = f"the {best['baseline']} baseline, " if best["baseline"] else ""
    words = (f"Pick from the measured table: trial {best['number']} ({which}{best[budget]:.4f}) is the best measured, "
             f"retrained alone and measured at {deploy}.")
    if estimates.empty:
        return words
    guess = estimates.iloc[0]
    if guess[budget] < best[budget]:
        words += (f" Trial {guess['number']}'s estimate ({guess[budget]:.4f}) looks lower but is not comparable: "
                  f"it is the {evaluator}'s figure at {train}, not a measurement.")
    return words + (f" To measure an estimate, `explorer export --study {study} --trial {guess['number']} --out "
                    f"trial{guess['number']}/` measures its paths at {deploy} (with the search's weights, not "
                    "retrained); resuming the search with a larger --finalists retrains more of the study's best "
                    "estimates.")


def print_rescored(view, frame: pd.DataFrame, args) -> None:
    """The measured table, the estimates' table (each sorted by the first budget, at most ``args.top``
    rows) and :func:`advice`; ``view``: the study's (explorer.study.view), for its settings."""
    from explorer.console import console, print_frame
    cfg = view.config
    deploy, train = ("x".join(map(str, size)) for size in (cfg.input_size, cfg.train_size))
    budget = args.budget[0]
    console.print(f"{args.study} re-scored for {args.device}: anytime loss ({args.metric}), lower is better, "
                  f"sorted by {budget}", markup=False, highlight=False)
    measured, estimates = frame[frame["figures"] == "measured"], frame[frame["figures"] != "measured"]
    if not measured.empty:
        print_frame(shown(measured, args.budget).head(args.top),
                    f"measured ({len(measured)}): retrained alone, measured at {deploy}")
    if not estimates.empty:
        print_frame(shown(estimates, args.budget).head(args.top),
                    f"estimates of the search ({len(estimates)}): {cfg.evaluator} at {train}, compare them with "
                    "each other only")
    console.print(advice(args.study, frame, budget, (deploy, train), cfg.evaluator), markup=False, highlight=False)
