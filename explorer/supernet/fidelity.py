"""How well a supernet of a given (space, data, recipe) ranks its space, as measured: the fidelity
experiment (bench_fidelity, ``experiments/fidelity.py``) scores supernets of a recipe against candidates trained
alone and stores its figures here, in ``fidelity.json`` (package data, so an installed copy has
them). A search's summary and report quote the entry for the study's own space and recipe, or say
that none exists."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from explorer.space import SearchSpace
from explorer.supernet.network import space_identity
from explorer.supernet.train import SupernetRecipe

FILE = Path(__file__).with_name("fidelity.json")


def fidelity_key(space: SearchSpace, data: str, recipe: SupernetRecipe) -> str:
    """The key of (space, data, recipe) in the record: the recipe's seed left out (the benchmark
    trains supernets with several seeds; a search's seed draws one of them)."""
    ident = recipe.identity()
    ident.pop("seed", None)
    text = json.dumps({"space": space_identity(space), "data": str(data), "recipe": ident}, sort_keys=True,
                      default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def load_record(file: Path = FILE) -> dict:
    try:
        return json.loads(Path(file).read_text())
    except (OSError, ValueError):
        return {}


def measured_fidelity(space: SearchSpace, data: str, recipe: SupernetRecipe, file: Path = FILE) -> dict | None:
    """The stored fidelity of supernets of (space, data, recipe), or None where none was measured:
    {"tau": [one per supernet], "spearman": [...], "recall": [...], "candidates": n, "label_steps": ...,
    "label_seeds": ..., "labels_seed_tau": ..., "finalist_tau": the finalists' recipe's tau, "date": ...}."""
    return load_record(file).get(fidelity_key(space, data, recipe))


def store_fidelity(space: SearchSpace, data: str, recipe: SupernetRecipe, entry: dict, file: Path = FILE) -> None:
    """Adds or replaces the entry of (space, data, recipe) in the record."""
    record = load_record(file)
    record[fidelity_key(space, data, recipe)] = {"space": space.name, "data": str(data),
                                                 "recipe": {k: v for k, v in recipe.identity().items() if k != "seed"},
                                                 **entry}
    Path(file).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")


def describe_fidelity(entry: dict | None) -> str:
    """One sentence on how far the supernet's estimate can be trusted, from a stored entry."""
    if not entry:
        return ("no fidelity measurement exists for this space, data and supernet recipe "
                "(the project's fidelity benchmark, in a clone of its repository, measures one): the estimate's "
                "ranking of the space is unmeasured")
    tau = entry["tau"]
    span = f"{min(tau):.2f}" if len(tau) == 1 else f"{min(tau):.2f}-{max(tau):.2f}"
    recall = entry.get("recall") or []
    low, high = (int(min(recall)), int(max(recall))) if recall else (0, 0)
    recall_text = f", {low if low == high else f'{low}-{high}'} of the best 5 in its best 10" if recall else ""
    spread = entry.get("labels_seed_tau")
    spread_text = f"; the labels' own seed-to-seed tau is {spread:.2f}" if spread is not None else ""
    finalist = entry.get("finalist_tau")
    # what the finalists' retraining itself ranks at: the scale against which to read the estimate's figure
    finalist_text = (f", and the same candidates trained alone with the finalists' recipe rank them at "
                     f"{finalist:.2f}" if finalist is not None else "")
    return (f"the supernet's ranking of this space was measured at Kendall tau {span} ({len(tau)} supernet(s)"
            f"{recall_text}) against {entry['candidates']} random candidates and the baselines trained alone "
            f"{entry['label_steps']} steps{spread_text}{finalist_text} ({entry.get('date', 'undated')})")
