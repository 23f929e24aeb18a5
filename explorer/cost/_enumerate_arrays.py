"""A whole space's costs as array arithmetic (``explorer.cost.enumerate``'s engine).

The space is the product of the axes ``SearchSpace.enumerate`` walks, in its order, so candidate ``r``
is row ``r`` of a grid and its choices are the mixed-radix digits of ``r``. A candidate's stages split
in two parts, each of which few axes determine: the *front* (everything before the first decoder
stage: the LiDAR-only exit, the LiDAR encoder, the image encoder and its exits, the ECU and exit 0)
and the *back* (the decoder stages and their exits). Each distinct front and back is costed once, from
``stage_specs`` of a representative candidate (stage costs cached by stage config, as per candidate);
a candidate's costs are its front's and its back's, added stage by stage in execution order, so every
latency is the same floating-point sum the per-candidate computation makes.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from functools import lru_cache
from typing import Any, Callable

import numpy as np
import pandas as pd

from explorer.anytime import BudgetDistribution
from explorer.errors import UserError
from explorer.cost.devices import DeviceProfile
from explorer.cost.workloads import stage_cost
from explorer.model.network import stage_specs
from explorer.space import Candidate, SearchSpace

#: the axes of ``SearchSpace.enumerate``'s product, outermost first
AXES = ("blocks", "width", "early", "widths", "exits", "heads", "lidar_exit", "residual", "precision", "downscale")
#: the axes that decide a candidate's front stages, and its back stages
FRONT_AXES = ("blocks", "width", "early", "front_exits", "heads", "lidar_exit", "residual", "downscale")
BACK_AXES = ("blocks", "width", "ecu", "widths", "back_exits", "heads", "residual", "downscale")
#: the most rows of a table of key texts over several axes
KEY_TABLE_ROWS = 1 << 16
COLUMNS = ("key", "encoder_blocks", "width_mult", "ecu", "decoder_widths", "exits", "head_depth", "paths",
           "params", "macs", "first_exit_ms", "last_exit_ms", "first_exit_j", "last_exit_j", "path_ms",
           "p_path0", "p_last", "budget_used")


def space_axes(space: SearchSpace) -> dict[str, list[dict[str, Any]]]:
    """Each axis of the space as the candidate fields its choices set, in ``SearchSpace.enumerate``'s order."""
    sized = [f for f in ("encoder_head_depth", "encoder_head_width", "ecu_head_depth", "ecu_head_width")
             if getattr(space, f) != (0,)]
    if sized:   # a position's heads exist only with its exit: not one more axis of the grid
        raise UserError(f"space '{space.name}' sizes exit heads per position (exits.{', exits.'.join(sized)}): "
                        "the space table does not cost such spaces yet; cost its candidates one at a time")
    ecu_options: list[dict[str, Any]] = []
    for on in space.ecu:
        lidar = itertools.product(space.lidar_depth, space.lidar_width, space.ecu_band, space.ecu_width) \
            if on else [(0, 0, 0, 0)]
        ecu_options += [dict(ecu=on, lidar_depth=d, lidar_width=w, ecu_band=b, ecu_width=e) for d, w, b, e in lidar]
    early = []
    for ecu in ecu_options:
        for mask in itertools.product((False, True), repeat=len(space.optional_encoder_exits)):
            enc = tuple(k for k, on in zip(space.optional_encoder_exits, mask) if on)
            orders = sorted(set(space.lidar_first)) if ecu["ecu"] and enc else [False]
            early += [{**ecu, "encoder_exits": enc, "lidar_first": first} for first in orders]
    last = len(space.decoder_widths)
    exit_sets = []
    for mask in itertools.product((False, True), repeat=len(space.optional_exits)):
        chosen = [e for e, on in zip(space.optional_exits, mask) if on]
        exit_sets.append({"exits": tuple(sorted(chosen + list(space.required_exits))) + (last,)})
    return {
        "blocks": [{"encoder_blocks": b} for b in space.encoder_blocks],
        "width": [{"width_mult": w} for w in space.width_mult],
        "early": early,
        "widths": [{"decoder_widths": w} for w in itertools.product(*space.decoder_widths)],
        "exits": exit_sets,
        "heads": [{"head_depth": d, "head_width": w} for d in space.head_depth
                  for w in (space.head_width if d == 2 else (0,))],
        "lidar_exit": [{"lidar_exit": v} for v in sorted(set(space.lidar_exit))],
        "residual": [{"exit_residual": v} for v in sorted(set(space.exit_residual))],
        "precision": [{"precision": p} for p in dict.fromkeys(space.precision)],
        "downscale": [{"downscale": d} for d in dict.fromkeys(space.downscale)],
    }


class _Ids:
    """Distinct values, numbered in the order first seen."""

    def __init__(self, values) -> None:
        self.values: list = list(dict.fromkeys(values))
        self.index = {v: i for i, v in enumerate(self.values)}

    def of(self, values) -> np.ndarray:
        return np.array([self.index[v] for v in values], dtype=np.int64)


class _Front:
    """Per distinct front, filled as rows need it: its parameters, MACs, time once its last stage ran
    (inference overhead included), its number of paths, its first path's ready time (NaN without
    one) and the ``path_ms`` text of its paths (each after a space)."""

    def __init__(self, n: int) -> None:
        self.done = np.zeros(n, dtype=bool)
        self.params, self.macs = np.zeros(n, np.int64), np.zeros(n, np.int64)
        self.end_ms, self.first_ms = np.zeros(n), np.full(n, np.nan)
        self.paths = np.zeros(n, np.int64)
        self.text = np.full(n, "", dtype=object)

    def fill(self, i: int, stages: list, overhead_ms: float) -> None:
        ms, ready = overhead_ms, []
        for p, m, t, completes_path in stages:   # the per-candidate sum's order: overhead, then each stage
            self.params[i], self.macs[i], ms = self.params[i] + p, self.macs[i] + m, ms + t
            if completes_path:
                ready.append(ms)
        self.end_ms[i], self.paths[i], self.done[i] = ms, len(ready), True
        self.first_ms[i] = ready[0] if ready else np.nan
        self.text[i] = "".join(f" {t:.3f}" for t in ready)


class _Back:
    """Per distinct back, filled as rows need it: parameters, MACs, each stage's time in execution
    order (0-padded: adding 0.0 changes no sum), which stage completes its q-th path (the last one
    repeated), and its number of paths."""

    def __init__(self, n: int) -> None:
        self.done = np.zeros(n, dtype=bool)
        self.params, self.macs = np.zeros(n, np.int64), np.zeros(n, np.int64)
        self.stage_ms, self.path_stage = np.zeros((n, 0)), np.zeros((n, 0), np.int64)
        self.paths = np.zeros(n, np.int64)

    def fill(self, i: int, stages: list) -> None:
        where = [j for j, s in enumerate(stages) if s[3]]
        if len(stages) > self.stage_ms.shape[1]:
            self.stage_ms = np.pad(self.stage_ms, ((0, 0), (0, len(stages) - self.stage_ms.shape[1])))
        if len(where) > self.path_stage.shape[1]:   # earlier rows repeat their last path's stage
            more = len(where) - self.path_stage.shape[1]
            self.path_stage = np.pad(self.path_stage, ((0, 0), (0, more)),
                                     mode="edge" if self.path_stage.shape[1] else "constant")
        self.stage_ms[i, :len(stages)] = [s[2] for s in stages]
        self.path_stage[i] = where + [where[-1]] * (self.path_stage.shape[1] - len(where))
        self.params[i], self.macs[i] = sum(s[0] for s in stages), sum(s[1] for s in stages)
        self.paths[i], self.done[i] = len(where), True


class SpaceGrid:
    """The space as a grid of axes: row ``r`` is the ``r``-th candidate ``SearchSpace.enumerate`` yields.
    :meth:`costs` costs any set of rows with array arithmetic (each distinct front and back costed the
    first time a row needs it); :meth:`frame` and :meth:`csv` turn those costs into the table's rows."""

    def __init__(self, space: SearchSpace, profile: DeviceProfile, dist: BudgetDistribution,
                 input_size: tuple[int, int]) -> None:
        self.space, self.profile, self.dist, self.input_size = space, profile, dist, tuple(input_size)
        self.axes = space_axes(space)
        self.shape = tuple(len(self.axes[a]) for a in AXES)
        self.size = math.prod(self.shape)
        self._ecu = _Ids(c["ecu"] for c in self.axes["early"])
        self._front_exits = _Ids(tuple(e for e in c["exits"] if e < 1) for c in self.axes["exits"])
        self._back_exits = _Ids(tuple(e for e in c["exits"] if e >= 1) for c in self.axes["exits"])
        self._stage_totals = stage_totals(profile)
        self._front = _Front(math.prod(self._part_shape(FRONT_AXES)))
        self._back = _Back(math.prod(self._part_shape(BACK_AXES)))
        self._keys = _KeyText(self)

    # -- candidates ----------------------------------------------------------------------------
    def digits(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        return dict(zip(AXES, np.unravel_index(np.asarray(rows, dtype=np.int64), self.shape)))

    def candidate(self, row: int) -> Candidate:
        """The candidate of row ``row`` (what ``SearchSpace.enumerate`` yields at that place)."""
        d = self.digits(np.array([row]))
        return Candidate(**{k: v for a in AXES for k, v in self.axes[a][int(d[a][0])].items()})

    def _representative(self, **choice: int) -> Candidate:
        """A candidate with the given axis choices; the other axes at a choice that fits them."""
        fields: dict[str, Any] = {}
        for a in AXES:
            fields.update(self.axes[a][choice.get(a, 0)])
        if "ecu" in choice:
            fields.update(next(c for c in self.axes["early"] if self._ecu.index[c["ecu"]] == choice["ecu"]))
        if "front_exits" in choice or "back_exits" in choice:
            ids, part = (self._front_exits, "front_exits") if "front_exits" in choice else (self._back_exits, "back_exits")
            fields.update(next(c for c in self.axes["exits"]
                               if ids.index[tuple(e for e in c["exits"] if (e < 1) == (part == "front_exits"))]
                               == choice[part]))
        return Candidate(**fields)

    def _split_costs(self, cand: Candidate) -> tuple[list, list]:
        """(front, back): per stage of ``cand`` in execution order (params, MACs, ms, completes a path)."""
        h, w = self.input_size
        shapes = {"image": (1, 3, h, w), "scan": (1, w)}
        staged = []
        for spec in stage_specs(cand):
            p, m, t, outs = self._stage_totals(spec.config, spec.name, tuple(shapes[n] for n in spec.inputs),
                                               h // 2 if spec.uses_scan_row else None)
            shapes.update(zip(spec.outputs, outs))
            staged.append((spec.name, p, m, t, spec.path is not None))
        first_back = next(i for i, s in enumerate(staged) if s[0].startswith("decoder_"))
        return [s[1:] for s in staged[:first_back]], [s[1:] for s in staged[first_back:]]

    # -- the distinct parts --------------------------------------------------------------------
    def _part_shape(self, axes: tuple[str, ...]) -> tuple[int, ...]:
        sizes = {**dict(zip(AXES, self.shape)), "ecu": len(self._ecu.values),
                 "front_exits": len(self._front_exits.values), "back_exits": len(self._back_exits.values)}
        return tuple(sizes[a] for a in axes)

    def parts(self, front: np.ndarray, back: np.ndarray) -> tuple[_Front, _Back]:
        """The distinct fronts and backs, costed first where ``front`` and ``back`` (indices) need it."""
        for i in np.unique(front[~self._front.done[front]]).tolist():
            choice = np.unravel_index(i, self._part_shape(FRONT_AXES))
            stages = self._split_costs(self._representative(**dict(zip(FRONT_AXES, map(int, choice)))))[0]
            self._front.fill(i, stages, self.profile.inference_overhead_ms)
        for i in np.unique(back[~self._back.done[back]]).tolist():
            choice = np.unravel_index(i, self._part_shape(BACK_AXES))
            self._back.fill(i, self._split_costs(self._representative(**dict(zip(BACK_AXES, map(int, choice)))))[1])
        return self._front, self._back

    def _part_index(self, d: dict[str, np.ndarray], axes: tuple[str, ...]) -> np.ndarray:
        ecu = self._ecu.of(c["ecu"] for c in self.axes["early"])
        front_exits = self._front_exits.of(tuple(e for e in c["exits"] if e < 1) for c in self.axes["exits"])
        back_exits = self._back_exits.of(tuple(e for e in c["exits"] if e >= 1) for c in self.axes["exits"])
        derived = {"ecu": ecu[d["early"]], "front_exits": front_exits[d["exits"]],
                   "back_exits": back_exits[d["exits"]]}
        return np.ravel_multi_index(tuple(derived[a] if a in derived else d[a] for a in axes),
                                    self._part_shape(axes))

    # -- rows ----------------------------------------------------------------------------------
    def costs(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """The numeric columns of ``rows``, plus the indices of their front and back."""
        d = self.digits(rows)
        f, b = self._part_index(d, FRONT_AXES), self._part_index(d, BACK_AXES)
        front, back = self.parts(f, b)
        ms = front.end_ms[f]
        after = np.empty((len(f), back.stage_ms.shape[1]))
        for j in range(back.stage_ms.shape[1]):   # stage by stage, as the per-candidate sum runs
            ms = ms + back.stage_ms[b, j]
            after[:, j] = ms
        back_ms = np.take_along_axis(after, back.path_stage[b], axis=1)
        n_front, n_back = front.paths[f], back.paths[b]
        first_ms = np.where(n_front > 0, front.first_ms[f], back_ms[:, 0])
        last_ms = back_ms[np.arange(len(b)), n_back - 1]
        first_j, last_j = (self.profile.energy_fixed_j + self.profile.active_power_w * t / 1000.0
                           for t in (first_ms, last_ms))
        first_cost, last_cost = (first_ms, last_ms) if self.dist.kind == "time" else (first_j, last_j)
        p_path0 = self.dist.cdf(first_cost) - self.dist.cdf(np.zeros(1))
        return {"digits": d, "front": f, "back": b, "back_ms": back_ms, "paths": n_front + n_back + 1,
                "params": front.params[f] + back.params[b], "macs": front.macs[f] + back.macs[b],
                "first_exit_ms": first_ms, "last_exit_ms": last_ms, "first_exit_j": first_j,
                "last_exit_j": last_j, "p_path0": p_path0, "p_last": 1.0 - self.dist.cdf(last_cost),
                "budget_used": 1.0 - p_path0}

    def frame(self, c: dict[str, np.ndarray]) -> pd.DataFrame:
        """The table ``candidate_rows`` makes, for the rows costed in ``c`` (:meth:`costs`)."""
        columns = {**self._choice_columns(c["digits"]), "path_ms": self._path_text(c)}
        for name in NUMERIC:
            columns[name] = c[name]
        return pd.DataFrame(columns, columns=list(COLUMNS))

    def csv(self, c: dict[str, np.ndarray]) -> str:
        """The lines of ``frame(c).to_csv(index=False, header=False)``, made without pandas: the
        choices' texts are made once per choice, a float's text is its ``repr`` (as pandas writes it)."""
        d = c["digits"]
        named = self._keys.keys(d)
        for column, (axis, field, fmt) in CHOICE_COLUMNS.items():
            named = named + np.array(["," + str(fmt(x[field]) if fmt else x[field]) for x in self.axes[axis]],
                                     dtype=object)[d[axis]]
        text = {"named": named, "path_ms": self._path_text(c)}
        text.update(_float_texts(c["first_exit_ms"], {k: c[k] for k in FIRST_PATH_COLUMNS}))
        for name in NUMERIC:
            if name not in text:
                text[name] = list(map(repr if c[name].dtype.kind == "f" else str, c[name].tolist()))
        order = ["named"] + [k for k in COLUMNS if k not in CHOICE_COLUMNS and k != "key"]
        return "\n".join(map(",".join, zip(*(text[k] for k in order)))) + "\n"

    def _choice_columns(self, d: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The columns that name a candidate's choices: its key, and what its axes' choices say."""
        out = {"key": self._keys.keys(d)}
        for column, (axis, field, fmt) in CHOICE_COLUMNS.items():
            values = [fmt(c[field]) if fmt else c[field] for c in self.axes[axis]]
            out[column] = np.array(values, dtype=object if fmt else None)[d[axis]]
        return out

    def _path_text(self, c: dict[str, np.ndarray]) -> list[str]:
        """Each path's ready time in ms to 3 decimals, space-separated (the front's texts made once)."""
        text = self._front.text[c["front"]]
        n_back = self._back.paths[c["back"]]
        for q in range(c["back_ms"].shape[1]):
            has = q < n_back
            formatted = np.full(len(text), "", dtype=object)
            formatted[has] = [f" {t:.3f}" for t in c["back_ms"][has, q].tolist()]
            text = text + formatted
        return [t[1:] for t in text]


#: the columns a candidate's choices give: (axis, field, how a value is written)
CHOICE_COLUMNS: dict[str, tuple[str, str, Callable | None]] = {
    "encoder_blocks": ("blocks", "encoder_blocks", None), "width_mult": ("width", "width_mult", None),
    "ecu": ("early", "ecu", None), "decoder_widths": ("widths", "decoder_widths", lambda v: "-".join(map(str, v))),
    "exits": ("exits", "exits", lambda v: "-".join(map(str, v))), "head_depth": ("heads", "head_depth", None),
}
NUMERIC = ("paths", "params", "macs", "first_exit_ms", "last_exit_ms", "first_exit_j", "last_exit_j", "p_path0",
           "p_last", "budget_used")


#: the columns that are functions of the first path's ready time alone
FIRST_PATH_COLUMNS = ("first_exit_ms", "first_exit_j", "p_path0", "budget_used")


def _float_texts(key: np.ndarray, columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``repr`` of each value of ``columns``, each a function of ``key``: made once per distinct ``key``
    (a float's bits decide it), which few rows' first paths have."""
    _, first, inverse = np.unique(key.view(np.int64), return_index=True, return_inverse=True)
    return {name: np.array(list(map(repr, values[first].tolist())), dtype=object)[inverse]
            for name, values in columns.items()}


def stage_totals(profile: DeviceProfile) -> Callable:
    """(params, MACs, ms, output shapes) of a stage, cached by its config and input shapes."""
    @lru_cache(maxsize=None)
    def totals(config, name: str, in_shapes: tuple, scan_row):
        records, out_shapes = stage_cost(config, name, in_shapes, scan_row)
        ms = float(sum(profile.layer_ms(w) for w in records)) + profile.stage_overhead_ms
        return (sum(w.params for w in records), sum(w.macs for w in records), ms, out_shapes)
    return totals


class _KeyText:
    """Candidate keys (``Candidate.key``: a hash of the sorted JSON of its fields) for many rows. Each
    field's JSON text is made once per choice of the axis that sets it; fields next to each other in
    sorted order are joined into tables over the few axes that set them, so a row's text is the
    concatenation of a couple of table entries."""

    def __init__(self, grid: SpaceGrid) -> None:
        owner = {field: a for a in AXES for field in grid.axes[a][0]}
        texts = {a: [grid._representative(**{a: i}).to_dict() for i in range(len(grid.axes[a]))] for a in AXES}
        groups: list[list[tuple[str, str]]] = [[]]
        for field in sorted(owner):
            axes = {a for a, _ in groups[-1]} | {owner[field]}
            if groups[-1] and math.prod(len(grid.axes[a]) for a in axes) > KEY_TABLE_ROWS:
                groups.append([])
            groups[-1].append((owner[field], field))
        self.sizes = {a: len(grid.axes[a]) for a in AXES}
        self.tables = [self._table(grid, group, texts) for group in groups]
        axes, table = self.tables[0]
        self.tables[0] = (axes, np.array([b"{" + t[1:] for t in table], dtype=object))   # no leading comma
        axes, table = self.tables[-1]
        self.tables[-1] = (axes, np.array([t + b"}" for t in table], dtype=object))

    @staticmethod
    def _table(grid: SpaceGrid, group: list[tuple[str, str]], texts: dict) -> tuple[tuple[str, ...], np.ndarray]:
        """(axes, text per combination of their choices) of a run of fields in sorted order."""
        axes = tuple(dict.fromkeys(a for a, _ in group))
        out = []
        for combo in itertools.product(*(range(len(grid.axes[a])) for a in axes)):
            choice = dict(zip(axes, combo))
            out.append("".join("," + json.dumps({f: texts[a][choice[a]][f]}, separators=(",", ":"))[1:-1]
                               for a, f in group if f in texts[a][choice[a]]).encode())
        return axes, np.array(out, dtype=object)

    def keys(self, d: dict[str, np.ndarray]) -> np.ndarray:
        text = None
        for axes, table in self.tables:
            index = np.ravel_multi_index(tuple(d[a] for a in axes), tuple(self.sizes[a] for a in axes)) \
                if len(axes) > 1 else d[axes[0]]
            text = table[index] if text is None else text + table[index]
        return np.array([hashlib.sha1(t).hexdigest()[:10] for t in text], dtype=object)
