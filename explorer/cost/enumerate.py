"""Cost-only enumeration of a whole space: parameters, MACs, per-path latency and energy, and the
cost side of the anytime loss, without building a torch module per candidate.

:func:`candidate_rows` costs candidates one by one (stage costs cached by stage config): the
reference. :func:`enumerate_space` and :func:`write_enumeration` give the same table for a whole space
with array arithmetic (``explorer.cost._enumerate_arrays``: each distinct stage configuration is
costed once, and a candidate's costs are sums of its stages' in execution order), stream it to CSV
(and Parquet where pyarrow is installed) chunk by chunk, and find the Pareto front of the costs over
every candidate.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import pandas as pd

from explorer.anytime import BudgetDistribution, interval_probabilities, parse_budget
from explorer.cost._enumerate_arrays import COLUMNS, SpaceGrid, stage_totals
from explorer.cost.devices import DeviceProfile, check_budget_priced, get_device
from explorer.errors import UserError
from explorer.files import writing_atomically
from explorer.model.network import stage_specs
from explorer.space import Candidate, SearchSpace

#: candidates costed, written and reported at a time: memory stays bounded whatever the space's size
CHUNK_ROWS = 100_000
#: columns a Pareto front may be taken over, and whether less (True) or more (False) is better
FRONT_COLUMNS = {"params": True, "macs": True, "first_exit_ms": True, "last_exit_ms": True,
                 "first_exit_j": True, "last_exit_j": True, "p_path0": True, "p_last": False, "budget_used": False}
#: the default front: halts left to the scan (the anytime loss's cost side), the whole network's
#: latency and its size, each the less the better
DEFAULT_FRONT = ("p_path0", "last_exit_ms", "params")

Progress = Callable[[int, int], None]


def candidate_rows(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
                   input_size: tuple[int, int] = (224, 224),
                   candidates: Iterable[Candidate] | None = None) -> Iterator[dict]:
    """One row per candidate of ``space`` (or of ``candidates``), costed one at a time: the reference
    that the array arithmetic of :func:`enumerate_space` reproduces exactly."""
    profile = get_device(device)
    dist = parse_budget(budget)
    check_budget_priced(profile, dist)
    totals = stage_totals(profile)
    h, w = input_size
    for cand in space.enumerate() if candidates is None else candidates:
        shapes = {"image": (1, 3, h, w), "scan": (1, w)}
        params = macs = 0
        ms = profile.inference_overhead_ms
        path_ms = [0.0]
        for spec in stage_specs(cand):
            p, m, t, outs = totals(spec.config, spec.name, tuple(shapes[n] for n in spec.inputs),
                                   h // 2 if spec.uses_scan_row else None)
            shapes.update(zip(spec.outputs, outs))
            params, macs, ms = params + p, macs + m, ms + t
            if spec.path is not None:
                path_ms.append(ms)
        energy = [0.0] + [profile.energy_fixed_j + profile.active_power_w * t / 1000.0 for t in path_ms[1:]]
        weights = interval_probabilities(path_ms if dist.kind == "time" else energy, dist)
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


def space_grid(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
               input_size: tuple[int, int] = (224, 224)) -> SpaceGrid:
    """The space as a grid whose rows (candidates, in ``space.enumerate()``'s order) are costed with
    array arithmetic; checks the budget against the device first."""
    profile = get_device(device)
    dist = parse_budget(budget)
    check_budget_priced(profile, dist)
    return SpaceGrid(space, profile, dist, input_size)


def _chunks(size: int) -> Iterator[np.ndarray]:
    for start in range(0, size, CHUNK_ROWS):
        yield np.arange(start, min(start + CHUNK_ROWS, size))


def enumerate_space(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
                    input_size: tuple[int, int] = (224, 224), progress: Progress | None = None) -> pd.DataFrame:
    """Every candidate's row (what :func:`candidate_rows` gives) as one table, in the space's order.
    It holds every row in memory: for a large space, :func:`write_enumeration` streams them instead."""
    grid = space_grid(space, device, budget, input_size)
    frames = []
    for rows in _chunks(grid.size):
        frames.append(grid.frame(grid.costs(rows)))
        if progress:
            progress(int(rows[-1]) + 1, grid.size)
    return pd.concat(frames, ignore_index=True)


def pareto_front(values: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the rows of ``values`` (n x k, the less the better in every column) that
    no other row dominates (no worse in every column, better in one). Equal rows do not dominate
    each other. Two columns: one sort and a running minimum; more: the front of a sample first
    discards most rows in a few array comparisons, then the rest are compared block by block."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or not len(values):
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort(values.T[::-1])
    ordered = values[order]
    new = np.ones(len(ordered), dtype=bool)
    new[1:] = (np.diff(ordered, axis=0) != 0).any(axis=1)
    distinct = ordered[new]
    group = np.cumsum(new) - 1
    keep = _front_of_sorted(distinct)
    return np.sort(order[keep[group]])


def _front_of_sorted(points: np.ndarray) -> np.ndarray:
    """Which of ``points`` (distinct, in lexicographic order) are not dominated: a dominating point
    always comes earlier."""
    n, k = points.shape
    if k == 1:
        return np.arange(n) == 0
    if k == 2:
        before = np.minimum.accumulate(np.concatenate(([np.inf], points[:-1, 1])))
        return points[:, 1] < before
    sample = np.unique(np.linspace(0, n - 1, min(n, 2000)).astype(np.int64))
    seeds = points[sample][_block_front(points[sample])]
    seeds = seeds[np.unique(np.linspace(0, len(seeds) - 1, min(len(seeds), 64)).astype(np.int64))]
    alive = np.ones(n, dtype=bool)
    for start in range(0, n, 20_000):
        block = points[start:start + 20_000]
        covered = (seeds[:, None, :] <= block[None, :, :]).all(axis=2)
        strictly = (seeds[:, None, :] < block[None, :, :]).any(axis=2)
        alive[start:start + 20_000] = ~(covered & strictly).any(axis=0)
    keep = np.zeros(n, dtype=bool)
    rest = np.flatnonzero(alive)
    keep[rest[_block_front(points[rest])]] = True
    return keep


def _block_front(points: np.ndarray, block: int = 1024) -> np.ndarray:
    """The non-dominated ones of ``points`` (distinct, lexicographic order), each block of points
    compared with the front so far and with itself."""
    front = np.zeros((0, points.shape[1]))
    keep = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), block):
        b = points[start:start + block]
        pool = np.concatenate([front, b])
        le = (pool[:, None, :] <= b[None, :, :]).all(axis=2)
        lt = (pool[:, None, :] < b[None, :, :]).any(axis=2)
        ok = ~(le & lt).any(axis=0)
        keep[start:start + block] = ok
        front = np.concatenate([front, b[ok]])
    return keep


def front_columns(text: str) -> tuple[str, ...]:
    """The columns of ``--front`` (comma-separated), checked."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in FRONT_COLUMNS]
    if not names or bad or len(set(names)) != len(names):
        raise UserError(f"--front {text!r}: give distinct columns, comma-separated, from {list(FRONT_COLUMNS)} "
                        f"(e.g. {','.join(DEFAULT_FRONT)})")
    return names


@dataclass
class Enumeration:
    """What :func:`write_enumeration` did: candidates costed, seconds taken, and the Pareto front."""

    size: int
    seconds: float
    front_columns: tuple[str, ...]
    front: pd.DataFrame      # every front candidate's row, sorted by the front's columns


def write_enumeration(space: SearchSpace, device: str | DeviceProfile, budget: str | BudgetDistribution,
                      input_size: tuple[int, int] = (224, 224), csv: str | Path | None = None,
                      parquet: str | Path | None = None, front: Iterable[str] = DEFAULT_FRONT,
                      progress: Progress | None = None) -> Enumeration:
    """Costs every candidate of ``space`` chunk by chunk, writes the rows to ``csv`` and ``parquet``
    (each whole or not at all: a scratch file renamed into place) and returns the Pareto front of the
    ``front`` columns over the whole space. Memory holds one chunk's rows and the front's columns."""
    t0 = time.perf_counter()
    front = tuple(front)
    writer = _parquet_writer() if parquet is not None else None
    grid = space_grid(space, device, budget, input_size)
    objectives = np.empty((grid.size, len(front)))
    with _scratch(csv, "w") as text, _scratch(parquet, "wb") as binary:
        if text:
            text.write(",".join(COLUMNS) + "\n")
        table = None
        for rows in _chunks(grid.size):
            costs = grid.costs(rows)
            if text:
                text.write(grid.csv(costs))
            if binary:
                table = writer.write(binary, table, grid.frame(costs))
            for j, name in enumerate(front):
                objectives[rows, j] = costs[name] if FRONT_COLUMNS[name] else -costs[name]
            if progress:
                progress(int(rows[-1]) + 1, grid.size)
        if table is not None:
            table.close()
    best = pareto_front(objectives)
    rows = grid.frame(grid.costs(best)).sort_values(list(front), ascending=[FRONT_COLUMNS[n] for n in front])
    return Enumeration(grid.size, time.perf_counter() - t0, front, rows.reset_index(drop=True))


@contextmanager
def _scratch(path: str | Path | None, mode: str):
    """A file opened beside ``path`` under a scratch name (``NAME.XXXX.tmpPID``), renamed onto ``path``
    when the block ends without an error, removed when it fails; nothing when ``path`` is None."""
    if path is None:
        yield None
        return
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{path}: cannot write it ({exc.strerror})") from None
    if not os.access(path.parent, os.W_OK):
        raise UserError(f"{path}: cannot write it (Permission denied)")
    with writing_atomically(path, mode) as f:
        yield f


class _ParquetChunks:
    """Writes frames to one Parquet file, chunk after chunk (pyarrow's ``ParquetWriter``)."""

    def __init__(self, pa, pq) -> None:
        self.pa, self.pq = pa, pq

    def write(self, sink, writer, frame: pd.DataFrame):
        table = self.pa.Table.from_pandas(frame, preserve_index=False)
        writer = writer or self.pq.ParquetWriter(sink, table.schema)
        writer.write_table(table)
        return writer


def _parquet_writer() -> _ParquetChunks:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise UserError("--parquet needs pyarrow: pip install 'anytime-explorer[parquet]' (or pyarrow), "
                        "or write --csv") from None
    return _ParquetChunks(pa, pq)
