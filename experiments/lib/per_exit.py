"""Where the estimate's ranking is lost, path by path, measured by bench_fidelity --per-exit.

A candidate's anytime loss weighs the errors of its paths (the interpolated scan, the LiDAR-only exit,
the fused encoder exits, the decoder exits) by how often each is the last one done in time. Two views
per kind of path: how well the supernet orders that path's error over the candidates that have it, and
how the anytime loss would rank were the supernet exact at that path alone (its error replaced by the
long labels'). The second says which path's estimate costs the ranking most, which is where a change
to the supernet should aim."""

from __future__ import annotations

from scipy.stats import kendalltau

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.space import Candidate

from experiments.lib.labels import BUDGET
from experiments.lib.predictor import path_kinds


def _by_kind(cand: Candidate, errors: list[float]) -> dict[str, float]:
    return dict(zip(path_kinds(cand), errors[1:]))


def path_taus(estimated: dict, labels: dict, least: int = 4) -> dict[str, tuple[float, float, int]]:
    """{path kind: (Kendall tau of the estimated against the labelled error over the candidates with that
    path, the mean overestimate, how many candidates)}, for kinds at least ``least`` candidates have.
    ``estimated`` and ``labels``: {candidate: per-path errors, path 0 first}."""
    pairs: dict[str, list[tuple[float, float]]] = {}
    for cand, errors in estimated.items():
        truth = _by_kind(cand, labels[cand])
        for kind, value in _by_kind(cand, errors).items():
            pairs.setdefault(kind, []).append((value, truth[kind]))
    return {kind: (float(kendalltau(*zip(*p)).statistic), float(sum(e - t for e, t in p) / len(p)), len(p))
            for kind, p in pairs.items() if len(p) >= least}


def exact_at_taus(estimated: dict, labels: dict) -> dict[str, float]:
    """{path kind: Kendall tau against the labels' anytime loss of the estimate's anytime loss with that
    kind's error taken from the labels}, and under "none" the estimate's own tau."""
    cands = list(estimated)
    costs = {c: candidate_cost(c).path_costs(get_device("tx2"), "time") for c in cands}
    truth = [anytime_loss(costs[c], labels[c], BUDGET) for c in cands]
    kinds = sorted({k for c in cands for k in path_kinds(c)})
    out = {}
    for kind in ["none"] + kinds:
        values = []
        for c in cands:
            errors = list(estimated[c])
            for i, k in enumerate(path_kinds(c), start=1):
                if k == kind:
                    errors[i] = labels[c][i]
            values.append(anytime_loss(costs[c], errors, BUDGET))
        out[kind] = float(kendalltau(values, truth).statistic)
    return out


def last_exit_taus(estimated: dict, labels: dict, least: int = 4) -> dict[str, float]:
    """{"plain", "residual": Kendall tau of the estimated against the labelled error at the last decoder
    exit, over the candidates with that head kind} (kinds with at least ``least`` candidates). Beside
    the same figure for a stand-alone recipe, it says whether the supernet orders an exit worse than
    training every candidate alone would."""
    out = {}
    for residual, name in ((False, "plain"), (True, "residual")):
        cands = [c for c in estimated if c.exit_residual == residual]
        if len(cands) >= least:
            out[name] = float(kendalltau([estimated[c][-1] for c in cands], [labels[c][-1] for c in cands]).statistic)
    return out
