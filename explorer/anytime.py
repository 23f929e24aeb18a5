"""The anytime loss (Eq. 1 of the paper, generalised to any budget distribution).

A network's paths are ready at costs c_0 = 0 < c_1 < ... < c_K (ms or J); at budget b the output is
the last path with c_i <= b, so with B the budget's distribution

    L = E_B[ l(f(B)) ] = sum_i l_i * P(c_i <= B < c_{i+1}),   c_{K+1} = +inf.

For B ~ U(0, B_max) this is Eq. 1, (1/B_max) sum_i l_i |P_i| with intervals clipped at B_max.
Everything is exact (no sampling). Distributions live in a registry, by name, and are written as
specs ``KIND:NAME:ARGS``: ``time:uniform:33ms``, ``energy:uniform:0.5J``,
``time:exponential:20ms`` (mean), ``time:truncnormal:20ms:5ms`` (mean, std, truncated at 0),
``time:trace:deadlines.csv`` (an empirical trace of measured deadlines, one per row).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from explorer.errors import UserError

UNITS = {
    "time": {"ms": 1.0, "s": 1000.0, "us": 1e-3},
    "energy": {"j": 1.0, "mj": 1e-3, "uj": 1e-6},
}
BASE_UNIT = {"time": "ms", "energy": "J"}
SPEC_HELP = ("budget specs are KIND:DIST:ARGS, e.g. time:uniform:33ms, energy:uniform:0.5J, "
             "time:exponential:20ms, time:truncnormal:20ms:5ms, time:trace:deadlines.csv")


class BudgetDistribution:
    """A budget's distribution: ``kind`` is 'time' (ms) or 'energy' (J); ``cdf`` is P(B <= b)."""

    kind: str = "time"
    name: str = ""

    def cdf(self, b: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @property
    def upper(self) -> float:
        """A budget beyond which the distribution has (almost) no mass: the end of plotted curves."""
        raise NotImplementedError

    @property
    def unit(self) -> str:
        return BASE_UNIT[self.kind]

    @property
    def spec(self) -> str:
        raise NotImplementedError

    def __str__(self) -> str:
        return self.spec


def _fmt(v: float, unit: str) -> str:
    return f"{v:g}{unit}"


@dataclass(frozen=True)
class Uniform(BudgetDistribution):
    """U(0, max): the paper's Eq. 1."""

    maximum: float
    kind: str = "time"
    name: str = field(default="uniform", init=False)

    def __post_init__(self) -> None:
        if not 0 < self.maximum < math.inf:
            raise UserError(f"uniform budget needs a positive, finite maximum, got {self.maximum}")

    def cdf(self, b):
        return np.clip(np.asarray(b, dtype=float) / self.maximum, 0.0, 1.0)

    @property
    def upper(self) -> float:
        return self.maximum

    @property
    def spec(self) -> str:
        return f"{self.kind}:uniform:{_fmt(self.maximum, self.unit)}"


@dataclass(frozen=True)
class Exponential(BudgetDistribution):
    """Exponential with the given mean: most halts come early."""

    mean: float
    kind: str = "time"
    name: str = field(default="exponential", init=False)

    def __post_init__(self) -> None:
        if not 0 < self.mean < math.inf:
            raise UserError(f"exponential budget needs a positive mean, got {self.mean}")

    def cdf(self, b):
        b = np.maximum(np.asarray(b, dtype=float), 0.0)
        return 1.0 - np.exp(-b / self.mean)

    @property
    def upper(self) -> float:
        return self.mean * 5

    @property
    def spec(self) -> str:
        return f"{self.kind}:exponential:{_fmt(self.mean, self.unit)}"


@dataclass(frozen=True)
class TruncatedNormal(BudgetDistribution):
    """Normal(mean, std) truncated to budgets >= 0: deadlines that cluster around a period."""

    mean: float
    std: float
    kind: str = "time"
    name: str = field(default="truncnormal", init=False)

    def __post_init__(self) -> None:
        if not 0 < self.std < math.inf or not math.isfinite(self.mean):
            raise UserError(f"truncnormal budget needs a positive std, got {self.std}")

    def _phi(self, x):
        return 0.5 * (1.0 + np.vectorize(math.erf)((np.asarray(x, dtype=float) - self.mean) / (self.std * math.sqrt(2))))

    def cdf(self, b):
        b = np.maximum(np.asarray(b, dtype=float), 0.0)
        low = self._phi(0.0)
        return (self._phi(b) - low) / (1.0 - low)

    @property
    def upper(self) -> float:
        return self.mean + 4 * self.std

    @property
    def spec(self) -> str:
        return f"{self.kind}:truncnormal:{_fmt(self.mean, self.unit)}:{_fmt(self.std, self.unit)}"


@dataclass(frozen=True)
class Trace(BudgetDistribution):
    """Empirical distribution of measured deadlines (e.g. from a robot's logs)."""

    values: tuple[float, ...]
    kind: str = "time"
    source: str = ""
    name: str = field(default="trace", init=False)

    def cdf(self, b):
        v = np.sort(np.asarray(self.values))
        return np.searchsorted(v, np.asarray(b, dtype=float), side="right") / len(v)

    @property
    def upper(self) -> float:
        return float(max(self.values))

    @property
    def spec(self) -> str:
        return f"{self.kind}:trace:{self.source}"

    @classmethod
    def from_csv(cls, path: str, kind: str, scale: float) -> "Trace":
        import pandas as pd
        p = Path(path)
        if p.is_dir():
            raise UserError(f"budget trace {path}: is a folder; give a CSV file with one deadline per row")
        if not p.is_file():
            raise UserError(f"budget trace {path}: no such file (a CSV with one deadline per row)")
        try:
            frame = pd.read_csv(p)
            if len(frame.columns) and all(_is_number(c) for c in frame.columns):   # no header: its first row is a deadline
                frame = pd.read_csv(p, header=None)
        except Exception as exc:  # pandas raises many types for malformed files
            raise UserError(f"budget trace {path}: unreadable CSV ({exc})") from None
        numeric = frame.select_dtypes("number")
        if numeric.empty or numeric.iloc[:, 0].dropna().empty:
            raise UserError(f"budget trace {path}: no numeric column of deadlines")
        column = numeric.columns[0]
        values = numeric[column].dropna().to_numpy(dtype=float)
        if not np.isfinite(values).all():
            raise UserError(f"budget trace {path}: deadlines must be finite (column '{column}' has inf)")
        if (values < 0).any():
            raise UserError(f"budget trace {path}: negative deadlines in column '{column}'")
        if not (values > 0).any():
            raise UserError(f"budget trace {path}: every deadline in column '{column}' is 0: nothing could run")
        # a column named like 'deadline_s' or 'budget_mj' says its unit
        m = re.search(r"_(ms|s|us|j|mj|uj)$", str(column).lower())
        if m and m.group(1) in UNITS[kind]:
            scale = UNITS[kind][m.group(1)]
        return cls(tuple(float(v) * scale for v in values), kind=kind, source=str(path))


def _is_number(text) -> bool:
    try:
        float(str(text))
    except ValueError:
        return False
    return True


def parse_quantity(text: str, kind: str) -> float:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e-?[0-9]+)?)\s*([a-zA-Z]*)\s*", text)
    if not m:
        raise UserError(f"'{text}' is not a {kind} quantity (e.g. {'33ms' if kind == 'time' else '0.5J'})")
    value, unit = float(m.group(1)), m.group(2).lower()
    if not math.isfinite(value):
        raise UserError(f"'{text}' is not a finite {kind} quantity")
    if not unit:
        unit = BASE_UNIT[kind].lower()
    if unit not in UNITS[kind]:
        raise UserError(f"unit '{m.group(2)}' is not a {kind} unit: use one of {sorted(UNITS[kind])}")
    return value * UNITS[kind][unit]


DISTRIBUTIONS: dict[str, Callable[[list[str], str], BudgetDistribution]] = {
    "uniform": lambda args, kind: Uniform(parse_quantity(_one(args, "uniform", "MAX"), kind), kind),
    "exponential": lambda args, kind: Exponential(parse_quantity(_one(args, "exponential", "MEAN"), kind), kind),
    "truncnormal": lambda args, kind: TruncatedNormal(*_two(args, kind), kind=kind),
    "trace": lambda args, kind: Trace.from_csv(":".join(args), kind, 1.0),
}


def _one(args: list[str], name: str, what: str) -> str:
    if len(args) != 1:
        raise UserError(f"{name} budget takes one argument ({what}): {SPEC_HELP}")
    return args[0]


def _two(args: list[str], kind: str) -> tuple[float, float]:
    if len(args) != 2:
        raise UserError(f"truncnormal budget takes MEAN:STD: {SPEC_HELP}")
    return parse_quantity(args[0], kind), parse_quantity(args[1], kind)


def parse_budget(spec: str | BudgetDistribution) -> BudgetDistribution:
    """A distribution from a spec such as ``time:uniform:33ms``."""
    if isinstance(spec, BudgetDistribution):
        return spec
    parts = str(spec).split(":")
    if len(parts) < 3:
        raise UserError(f"budget '{spec}' is incomplete: {SPEC_HELP}")
    kind, name, args = parts[0].lower(), parts[1].lower(), parts[2:]
    if kind not in UNITS:
        raise UserError(f"budget '{spec}': kind '{parts[0]}' is not one of {sorted(UNITS)}")
    if name not in DISTRIBUTIONS:
        raise UserError(f"budget '{spec}': distribution '{parts[1]}' is not one of {sorted(DISTRIBUTIONS)}")
    return DISTRIBUTIONS[name](args, kind)


def _check(costs: Sequence[float], losses: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(costs, dtype=float)
    l = np.asarray(losses, dtype=float)
    if c.ndim != 1 or c.shape != l.shape or len(c) == 0:
        raise UserError(f"costs and losses must be two lists of the same length, got {len(c)} and {len(l)}")
    if (c < 0).any() or not np.isfinite(c).all():
        raise UserError(f"costs must be finite and non-negative, got {[float(x) for x in c]}")
    if np.any(np.diff(c) < 0):
        raise UserError(f"path costs must not decrease (paths are prefixes of one run), got {[float(x) for x in c]}")
    return c, l


def check_losses(losses: Sequence[float]) -> np.ndarray:
    """Per-path losses a user gives (``explorer anytime``): finite and non-negative, as errors are."""
    l = np.asarray(losses, dtype=float)
    if not np.isfinite(l).all() or (l < 0).any():
        raise UserError(f"losses must be finite and non-negative (errors such as RMSE), got {[float(x) for x in l]}")
    return l


def interval_probabilities(costs: Sequence[float], budget: str | BudgetDistribution) -> np.ndarray:
    """P(c_i <= B < c_{i+1}) for each path: the weight of its loss."""
    dist = parse_budget(budget)
    c = np.asarray(costs, dtype=float)
    edges = np.append(dist.cdf(c), 1.0)
    return np.diff(edges)


def exit_loss_weights(costs: Sequence[float], budget: str | BudgetDistribution, floor: float = 0.25
                      ) -> tuple[float, ...]:
    """Training-loss weights for paths 1..K that follow each path's weight in the anytime loss
    (:func:`interval_probabilities`), mixed with equal weights by ``floor`` so that a path the budget
    rarely reaches still learns (another budget or device may reach it). They sum to 1."""
    if not 0.0 <= floor <= 1.0:
        raise UserError(f"exit weight floor must lie in [0, 1], got {floor}")
    share = interval_probabilities(costs, budget)[1:]
    k = len(share)
    if k == 0:
        return ()
    total = share.sum()
    share = share / total if total > 0 else np.full(k, 1.0 / k)
    return tuple(float(w) for w in (1.0 - floor) * share + floor / k)


def returned_losses(losses: Sequence[float]) -> np.ndarray:
    """The loss of what a halt after each path returns: the most accurate path ready by then (the
    runtime never hands back a path less accurate than one it already has), so the running minimum."""
    return np.minimum.accumulate(np.asarray(losses, dtype=float))


def anytime_loss(costs: Sequence[float], losses: Sequence[float], budget: str | BudgetDistribution) -> float:
    """Expected loss when inference halts at a budget drawn from ``budget``.

    ``costs`` and ``losses`` list every path, path 0 included (cost 0). A halt returns the most
    accurate path ready by then (:func:`returned_losses`): the last one ready wherever each path
    improves on those before it, as the paper's Eq. 1 has it. Halts before the first path (possible
    when path 0 is left out, or a trace has budgets below c_0) return the first path's loss:
    nothing better exists.
    """
    c, l = _check(costs, losses)
    l = returned_losses(l)
    dist = parse_budget(budget)
    edges = np.append(dist.cdf(c), 1.0)
    edges[0] = 0.0
    return float(np.dot(l, np.diff(edges)))


def anytime_curve(costs: Sequence[float], losses: Sequence[float],
                  upper: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The step curve budget -> loss, as (budgets, losses) ready for ``plt.step(where='post')``;
    the area under it up to B_max, divided by B_max, is the uniform anytime loss."""
    c, l = _check(costs, losses)
    l = returned_losses(l)
    upper = float(upper if upper is not None else c[-1] * 1.1 or 1.0)
    keep = c < upper
    xs = np.append(c[keep], upper)
    ys = np.append(l[keep], l[keep][-1])
    return xs, ys
