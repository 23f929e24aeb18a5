"""Cost-only enumeration of a whole space: parameters, MACs, per-path latency and energy, and the
cost side of the anytime loss, without building a torch module per candidate (stage costs are
cached by stage config, and most candidates share most stages)."""

from __future__ import annotations

from functools import lru_cache
from typing import Callable, Iterator

import pandas as pd

from explorer.anytime import BudgetDistribution, interval_probabilities, parse_budget
from explorer.cost.devices import DeviceProfile, check_budget_priced, get_device
from explorer.cost.workloads import stage_cost
from explorer.model.network import stage_specs
from explorer.space import SearchSpace


def _stage_totals(profile: DeviceProfile) -> Callable:
    @lru_cache(maxsize=None)
    def totals(config, name: str, in_shapes: tuple, scan_row):
        records, out_shapes = stage_cost(config, name, in_shapes, scan_row)
        ms = float(sum(profile.layer_ms(w) for w in records)) + profile.stage_overhead_ms
        return (sum(w.params for w in records), sum(w.macs for w in records), ms, out_shapes)
    return totals


def candidate_rows(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
                   input_size: tuple[int, int] = (224, 224)) -> Iterator[dict]:
    profile = get_device(device)
    dist = parse_budget(budget)
    check_budget_priced(profile, dist)
    totals = _stage_totals(profile)
    h, w = input_size
    for cand in space.enumerate():
        shapes = {"image": (1, 3, h, w), "scan": (1, w)}
        params = macs = 0
        ms = profile.inference_overhead_ms
        path_ms, path_params, path_macs = [0.0], [0], [0]
        for spec in stage_specs(cand):
            p, m, t, outs = totals(spec.config, spec.name, tuple(shapes[n] for n in spec.inputs),
                                   h // 2 if spec.uses_scan_row else None)
            shapes.update(zip(spec.outputs, outs))
            params, macs, ms = params + p, macs + m, ms + t
            if spec.path is not None:
                path_ms.append(ms)
                path_params.append(params)
                path_macs.append(macs)
        energy = [0.0] + [profile.energy_fixed_j + profile.active_power_w * t / 1000.0 for t in path_ms[1:]]
        costs = path_ms if dist.kind == "time" else energy
        weights = interval_probabilities(costs, dist)
        yield {"key": cand.key, "encoder_blocks": cand.encoder_blocks, "width_mult": cand.width_mult,
               "ecu": cand.ecu, "decoder_widths": "-".join(map(str, cand.decoder_widths)),
               "exits": "-".join(map(str, cand.exits)), "head_depth": cand.head_depth,
               "paths": len(path_ms), "params": params, "macs": macs,
               "first_exit_ms": path_ms[1], "last_exit_ms": path_ms[-1],
               "first_exit_j": energy[1], "last_exit_j": energy[-1],
               "path_ms": " ".join(f"{t:.3f}" for t in path_ms[1:]),
               "p_path0": float(weights[0]),           # halts that only get the scan
               "p_last": float(weights[-1]),           # halts that get the full network
               "budget_used": float(1.0 - weights[0])}


def enumerate_space(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
                    input_size: tuple[int, int] = (224, 224),
                    progress: Callable[[int, int], None] | None = None) -> pd.DataFrame:
    rows = []
    total = space.size
    for i, row in enumerate(candidate_rows(space, device, budget, input_size), start=1):
        rows.append(row)
        if progress and (i % 500 == 0 or i == total):
            progress(i, total)
    return pd.DataFrame(rows)
