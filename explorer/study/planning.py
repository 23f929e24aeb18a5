"""A run's time limit: how ``explorer search --time-limit`` fits data generation, supernet training,
sampling and the finalists' retraining into one wall-clock budget on whatever machine it runs on.

The same search can take three times as long on one machine as on another of the same size
(slower training steps). So the run measures the machine first (a few training steps of the paper design
and of the supernet, a few seconds), then sizes what may give, in this order:

- the finalists keep their recipe where the supernet's full steps fit beside it, else their steps
  shrink to ``KEEP_STEPS`` of it first (only settings a user did not give ever give way);
- the supernet, when its steps are not given, gets what is left but sampling's minimum, between
  ``MIN_SUPERNET_STEPS`` and ``MAX_SUPERNET_STEPS`` (rounded to ``STEP_GRID`` so that runs on one
  machine share the cached one);
- sampling gets what is then left, up to its ``--timeout``.
  The maximum is the default recipe's 600: a 1,500-step supernet did not find better candidates
  (retrained ratio to the paper design 0.877 against 0.865, one study each), so a fast machine
  does not train longer; the time the finalists leave goes to the envelope's dedicated networks
  (``search._envelope_in_time_left``), each only if it ends before the limit.

So when time is short, sampling shrinks first (to ``MIN_SAMPLING_S``), then the finalists' steps (to
``KEEP_STEPS`` of theirs), then the supernet (to its minimum), then the number of finalists (to one),
then the finalists' steps again (to ``MIN_FINALIST_STEPS``). What was changed is
said to the user and stored on the study (``plan``). The finalists are re-planned before they start
(sampling and the supernet may have run long, the machine may have slowed): then their steps give
way first, down to two thirds, so that one finalist per image encoder is kept where it can be; the
finalists that re-plan drops are retrained last when the others' real time says they fit
(``finalists.retrain_finalists(extra=, deadline=)``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

from explorer.model import build_model, build_network
from explorer.space import SearchSpace, paper_candidate
from explorer.study.config import baseline_model
from explorer.supernet.pace import seconds_per_step
from explorer.training.train import train

MIN_SAMPLING_S = 60.0
MIN_SUPERNET_STEPS = 300
MAX_SUPERNET_STEPS = 600
STEP_GRID = 100
MIN_FINALIST_STEPS = 150
RESERVE_S = 20.0        # the report, the last costings, the process's exit
SAFETY = 1.1            # measured step times are a few steps of a noisy machine: a margin on them, and
                        # no more (a larger one leaves the time limit's end unused)
FINALIST_SIZE = 1.3     # finalists not measured yet train this much slower than the paper design
                        # (measured when sampling ends)
KEEP_STEPS = 2 / 3      # when re-planned short, the finalists' steps shrink this far before their number does


@dataclass(frozen=True)
class Speeds:
    """Seconds per step on this machine, measured a moment ago."""

    retrain_step_s: float        # the paper design, the study's training recipe
    retrain_eval_s: float        # its validation pass after training
    supernet_step_s: float       # one sandwich step (0 when no supernet is trained)
    baseline_step_s: tuple[tuple[str, float], ...] = ()   # the other baselines, same recipe
    finalist_step_s: tuple[float, ...] = ()   # the finalists chosen so far, best first, same recipe
    tune_s: float = 0.0          # the paper design's tuning phase at the deployment size, its measurement included

    def relative_training(self, baseline: str) -> float | None:
        """A baseline's training step over the paper design's, if it was measured."""
        step = dict(self.baseline_step_s).get(baseline)
        return step / self.retrain_step_s if step and self.retrain_step_s > 0 else None

    def finalist_load(self, count: int) -> float:
        """The first ``count`` finalists' training in paper designs' worth: measured when they are
        known (at the end of sampling), else ``FINALIST_SIZE`` each."""
        if count <= len(self.finalist_step_s) and self.retrain_step_s > 0:
            return sum(self.finalist_step_s[:count]) / self.retrain_step_s
        return count * FINALIST_SIZE


@dataclass(frozen=True)
class Plan:
    """What the run will do, and how long each part is expected to take."""

    limit_s: float
    supernet_steps: int          # 0 when the evaluator needs none
    supernet_s: float            # 0 when the supernet is cached
    sampling_s: float
    finalists: int
    finalist_steps: int
    retrain_jobs: int            # finalists plus baselines
    retrain_s: float
    changes: tuple[str, ...] = ()
    trial_s: float = 0.0         # a trial started just before the sampling deadline may run this long
    tune: str = ""               # the retrainings' tuning at the deployment size, in words ("" = none)
    fits: bool = True            # False when even the smallest settings need more than the time limit
    not_retrained: int = 0       # finalists and baselines asked for that the time limit left untrained

    @property
    def expected_s(self) -> float:
        return self.supernet_s + self.sampling_s + self.retrain_s + RESERVE_S

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "changes": list(self.changes)}

    def describe(self) -> str:
        supernet = (f"supernet {self.supernet_steps} steps (~{self.supernet_s / 60:.1f} min)" if self.supernet_s
                    else f"supernet {self.supernet_steps} steps (cached)" if self.supernet_steps
                    else "no supernet (each candidate trained alone)")
        tune = f" + {self.tune}" if self.tune else ""
        retrain = (f"{self.finalists} finalist(s) and {self.retrain_jobs - self.finalists} baseline(s) retrained "
                   f"{self.finalist_steps} steps{tune} (~{self.retrain_s / 60:.1f} min)" if self.retrain_jobs else
                   "no retraining")
        return (f"plan for --time-limit {self.limit_s / 60:g}m: {supernet}, sampling {self.sampling_s / 60:.1f} min, "
                f"{retrain}")


def retrain_seconds(speeds: Speeds, finalists: int, baselines: float, steps: int) -> float:
    """``baselines`` counts paper designs' worth of training (a reference network counts more)."""
    jobs = speeds.finalist_load(finalists) + baselines
    return SAFETY * jobs * (steps * speeds.retrain_step_s + speeds.retrain_eval_s + speeds.tune_s) if jobs else 0.0


def plan_run(remaining_s: float, limit_s: float, speeds: Speeds, *, sampling_s: float | None,
             supernet_steps: int, supernet_free: bool, supernet_cached: bool, finalists: int,
             finalists_free: bool, finalist_steps: int, finalist_steps_free: bool, baselines: float,
             trial_s: float = 0.0, baseline_count: int | None = None) -> Plan:
    """Sizes the run to ``remaining_s`` seconds. ``*_free`` says which settings the user left to the plan;
    ``sampling_s`` is the user's cap on sampling (None: none, the plan gives it what is left);
    ``trial_s`` is how long a trial started just before the sampling deadline may run past it;
    ``baselines`` is their training in paper designs' worth, ``baseline_count`` how many they are."""
    changes: list[str] = []
    baseline_count = round(baselines) if baseline_count is None else baseline_count
    if not finalists:   # the baselines are retrained beside finalists only
        baselines, baseline_count = 0, 0
    budget = remaining_s - RESERVE_S - trial_s
    sampling_want = sampling_s if sampling_s is not None else math.inf
    sampling_min = min(MIN_SAMPLING_S, sampling_want)

    def supernet_cost(steps: int) -> float:
        return 0.0 if supernet_cached else SAFETY * steps * speeds.supernet_step_s

    def retrain(n: int, steps: int) -> float:
        return retrain_seconds(speeds, n, baselines, steps)

    if supernet_free and not supernet_cached and speeds.supernet_step_s > 0 and finalist_steps_free:
        # the supernet's steps decide how well every candidate is ranked (bench_fidelity measures the
        # ranking), the finalists' steps only which of a few
        # near-equal ones wins: they give way first, to KEEP_STEPS, so that the supernet keeps its steps
        room = budget - sampling_min - supernet_cost(supernet_steps)
        steps = _steps_that_fit(lambda k: retrain(finalists, k), finalist_steps, room,
                                max(MIN_FINALIST_STEPS, int(finalist_steps * KEEP_STEPS)))
        if steps != finalist_steps:
            changes.append(f"finalists retrained {steps} steps instead of {finalist_steps}")
            finalist_steps = steps
    if supernet_free and not supernet_cached and speeds.supernet_step_s > 0:
        # sampling gives way first (its best estimate comes early: trial 178 of 481 in a default study),
        # so the supernet may take all but sampling's minimum
        spare = budget - retrain(finalists, finalist_steps) - sampling_min
        fit = int(spare / (SAFETY * speeds.supernet_step_s) // STEP_GRID * STEP_GRID)
        chosen = max(MIN_SUPERNET_STEPS, min(MAX_SUPERNET_STEPS, fit))
        if chosen != supernet_steps:
            changes.append(f"supernet {chosen} steps ({speeds.supernet_step_s:.2f} s a step here)")
        supernet_steps = chosen
    left = budget - supernet_cost(supernet_steps) - retrain(finalists, finalist_steps)
    if left < sampling_min and finalists_free and finalists > 1:
        fewer = finalists
        while fewer > 1 and budget - supernet_cost(supernet_steps) - retrain(fewer, finalist_steps) < sampling_min:
            fewer -= 1
        changes.append(f"{fewer} finalist(s) instead of {finalists}")
        finalists = fewer
        left = budget - supernet_cost(supernet_steps) - retrain(finalists, finalist_steps)
    if left < sampling_min and finalist_steps_free and finalist_steps > MIN_FINALIST_STEPS:
        per_step = retrain(finalists, finalist_steps) / max(finalist_steps, 1)
        room = budget - supernet_cost(supernet_steps) - sampling_min
        steps = max(MIN_FINALIST_STEPS, int(room / per_step) if per_step > 0 else finalist_steps)
        steps = min(steps, finalist_steps)
        if steps != finalist_steps:
            changes.append(f"finalists retrained {steps} steps instead of {finalist_steps}")
            finalist_steps = steps
        left = budget - supernet_cost(supernet_steps) - retrain(finalists, finalist_steps)
    sampling = max(min(sampling_want, left), sampling_min)
    if math.isfinite(sampling_want) and sampling < sampling_want:
        changes.append(f"sampling {sampling / 60:.1f} min instead of {sampling_want / 60:.1f}")
    plan = Plan(limit_s=limit_s, supernet_steps=supernet_steps, supernet_s=supernet_cost(supernet_steps),
                sampling_s=sampling, finalists=finalists, finalist_steps=finalist_steps,
                retrain_jobs=finalists + baseline_count if (finalists or baseline_count) else 0,
                retrain_s=retrain(finalists, finalist_steps), changes=tuple(changes), trial_s=trial_s)
    if plan.expected_s > remaining_s + 1:
        plan = dataclasses.replace(plan, fits=False, changes=plan.changes + (
            f"this machine needs about {plan.expected_s / 60:.0f} min even so: give a longer --time-limit",))
    return plan


def _steps_that_fit(seconds, steps: int, room: float, floor: int) -> int:
    """The most steps up to ``steps``, and not under ``floor``, whose ``seconds(steps)`` fit in ``room``
    (a fixed part, the validation passes, plus a part per step)."""
    fixed = seconds(0)
    per_step = (seconds(steps) - fixed) / max(steps, 1)
    if per_step <= 0 or seconds(steps) <= room:
        return steps
    return min(steps, max(floor, int((room - fixed) / per_step)))


def replan_sampling(plan: Plan, remaining_s: float, sampling_s: float | None) -> Plan:
    """Sampling sized again once the supernet is trained: it gets what the supernet's phase left
    (more when it ran faster than measured, less when the machine slowed), up to the cap ``sampling_s``."""
    want = sampling_s if sampling_s is not None else math.inf
    left = remaining_s - RESERVE_S - plan.trial_s - plan.retrain_s
    sampling = max(min(want, left), min(MIN_SAMPLING_S, want))
    if abs(sampling - plan.sampling_s) < 5:
        return plan
    return dataclasses.replace(plan, sampling_s=sampling, changes=plan.changes + (
        f"sampling re-planned after the supernet, with {remaining_s / 60:.1f} min left: {sampling / 60:.1f} min",))


def supernet_deadline(plan: Plan, limit: "TimeLimit", speeds: Speeds, paper_baseline: bool,
                      sampling_s: float | None) -> float:
    """The latest moment (a time.time()) the supernet may train until: what comes after it needs, at
    its least, sampling's minimum, the best finalist and the paper design at ``MIN_FINALIST_STEPS``, and
    the reserve. Before that, a supernet that runs long takes its time from sampling (which shrinks
    first); past it, the supernet stops where it is and the study goes on with it as trained so far."""
    want = sampling_s if sampling_s is not None else math.inf
    retrain = retrain_seconds(speeds, 1, 1.0 if paper_baseline else 0.0, MIN_FINALIST_STEPS) if plan.finalists else 0.0
    return limit.ends - RESERVE_S - plan.trial_s - min(MIN_SAMPLING_S, want) - retrain


def replan_finalists(plan: Plan, remaining_s: float, speeds: Speeds, baselines: float, steps_free: bool,
                     finalists_free: bool, baseline_count: int | None = None,
                     wanted: tuple[int, int] | None = None) -> Plan:
    """The finalists' part, sized again to the time really left when sampling has ended, with
    ``speeds`` measured again just before: their steps shrink first (to ``KEEP_STEPS`` of the
    recipe), then their number, then their steps to the minimum. ``wanted`` (finalists, steps) is
    what was asked before the first plan shrank them: a machine that was busy when first measured
    gets them back."""
    baseline_count = round(baselines) if baseline_count is None else baseline_count
    finalists, steps, changes = plan.finalists, plan.finalist_steps, list(plan.changes)
    if wanted is not None:
        finalists = max(finalists, wanted[0]) if finalists_free else finalists
        steps = max(steps, wanted[1]) if steps_free else steps
    budget = remaining_s - RESERVE_S

    def fit_steps(floor: int) -> int:
        if not steps_free:
            return steps
        return _steps_that_fit(lambda k: retrain_seconds(speeds, finalists, baselines, k), steps, budget, floor)

    # The finalists' number is what turns the supernet's encoder bias around (one per encoder), so
    # their steps give way first, to KEEP_STEPS of the recipe; then their number; then the steps again.
    steps = fit_steps(max(MIN_FINALIST_STEPS, int(steps * KEEP_STEPS)))
    while finalists_free and finalists > 1 and retrain_seconds(speeds, finalists, baselines, steps) > budget:
        finalists -= 1
    steps = fit_steps(MIN_FINALIST_STEPS)
    if (finalists, steps) != (plan.finalists, plan.finalist_steps):
        relative = [step / speeds.retrain_step_s for step in speeds.finalist_step_s[:finalists]
                    if speeds.retrain_step_s > 0]
        measured = f", the finalists' {min(relative):.2f}-{max(relative):.2f}x that" if relative else ""
        changes.append(f"finalists re-planned with {remaining_s / 60:.1f} min left ({speeds.retrain_step_s:.2f} s "
                       f"a step here now{measured}): {finalists} retrained {steps} steps")
    return dataclasses.replace(plan, finalists=finalists, finalist_steps=steps,
                               retrain_jobs=finalists + baseline_count if (finalists or baseline_count) else 0,
                               retrain_s=retrain_seconds(speeds, finalists, baselines, steps),
                               changes=tuple(changes))


def not_retrained(skipped: int, plan: Plan, left_s: float) -> str:
    """The plan's change for ``skipped`` finalists or baselines that the time limit stopped, when the
    retraining had ``left_s`` seconds: the plan's own retraining needed more (settings the user fixed,
    or minimums, that no plan fits), or the machine ran slower than the plan measured."""
    if plan.retrain_s > left_s + 1:
        return (f"{skipped} finalist(s) or baseline(s) not retrained: the retraining planned needed about "
                f"{plan.retrain_s / 60:.1f} min and the time limit left {max(left_s, 0) / 60:.1f} "
                "(give a longer --time-limit)")
    return (f"{skipped} finalist(s) or baseline(s) not retrained: the machine ran slower than planned and the "
            "time limit came first")


# -- measuring ------------------------------------------------------------------------------------
def _seconds_per_step(marks: dict[int, float]) -> float:
    """The median step after the first two (in a fresh process they run slower: allocation, first
    kernels), from the times at which each step ended."""
    import statistics
    steps = sorted(marks)
    times = [marks[b] - marks[a] for a, b in zip(steps, steps[1:]) if a >= 2] or \
            [marks[b] - marks[a] for a, b in zip(steps, steps[1:])]
    return statistics.median(times) if times else 0.0


def measure_speeds(config, train_set, val_set, device, supernet: "SearchSpace | None", steps: int = 6,
                   baselines: tuple[str, ...] = (), finalists: tuple = (), deployment=None) -> Speeds:
    """A few steps of the paper design with the study's recipe, of each baseline named in ``baselines``
    and each candidate in ``finalists`` with the same recipe and, when one must be trained, of the
    ``supernet`` space's supernet with its recipe (each of its phases, :mod:`explorer.supernet.pace`; None:
    none): the median seconds a step, warm-up left out. With
    ``deployment`` (:class:`~explorer.training.deployment.DeploymentData`) and a recipe that tunes, the
    paper design's tuning phase too: a few steps at the deployment size and its measurement there."""
    import torch

    marks: dict[int, float] = {}
    recipe = dataclasses.replace(config.finalist_config(), steps=steps)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    result = train(build_network(paper_candidate()), train_set, val_set, recipe, device,
                   progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()),
                   val_limit=config.val_limit)
    retrain_step = _seconds_per_step(marks)
    retrain_eval = max(time.perf_counter() - t0 - result.seconds, 0.0)

    def step_of(model) -> float:
        marks: dict[int, float] = {}
        torch.manual_seed(0)
        train(build_model(model), train_set, val_set, recipe, device, val_limit=1,
              progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()))
        return _seconds_per_step(marks)

    tune_s = _tune_seconds(config, deployment, device) if deployment is not None else 0.0
    baseline_steps = tuple((name, step_of(baseline_model(name))) for name in baselines)
    finalist_steps = tuple(step_of(candidate) for candidate in finalists)
    supernet_step = seconds_per_step(supernet, config.data, config.supernet_recipe(), device) if supernet else 0.0
    return Speeds(retrain_step, retrain_eval, supernet_step, baseline_steps, finalist_steps, tune_s)


def _tune_seconds(config, deployment, device, steps: int = 4) -> float:
    """The paper design's tuning phase at the deployment size, from ``steps`` of it: its steps and its
    validation pass there (0 when the recipe does not tune)."""
    import torch
    recipe = config.finalist_recipe()
    if not recipe.tunes:
        return 0.0
    marks: dict[int, float] = {}
    tune = dataclasses.replace(recipe.tune_config(), steps=steps)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    result = train(build_network(paper_candidate()), deployment.deploy_train, deployment.deploy_val, tune, device,
                   progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()), val_limit=config.val_limit)
    evaluation = max(time.perf_counter() - t0 - result.seconds, 0.0)
    return recipe.tune_steps * _seconds_per_step(marks) + evaluation


@dataclass(frozen=True)
class TimeLimit:
    """``--time-limit``: the wall-clock seconds of the whole run, counted from ``started``; ``free`` names
    the settings the user left to the plan (``supernet_steps``, ``finalists``, ``finalist_steps``)."""

    seconds: float
    started: float = dataclasses.field(default_factory=time.time)
    free: frozenset[str] = frozenset({"supernet_steps", "finalists", "finalist_steps"})

    @property
    def ends(self) -> float:
        """When the run must be over (a time.time())."""
        return self.started + self.seconds

    def remaining(self) -> float:
        return self.ends - time.time()
