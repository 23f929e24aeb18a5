"""The search: Optuna over a search space, minimising the anytime loss on a device.

Each trial samples a candidate, costs its paths on the device (no training), rejects it if a
constraint rules it out, estimates its per-path accuracy with an evaluator (a slice of the space's
trained supernet, about a second; or proxy training, reporting the anytime loss so hopeless ones are
pruned), and stores everything re-scoring needs. The paper's design, the same without early exits,
and a FastDepth-like network are the study's first trials (when the evaluator can estimate them),
tagged as baselines. A study ends by retraining its best candidates and the baselines stand-alone
with a longer recipe (the finalists): the winner a user reads about is always a retrained one.
"""


import dataclasses
import gc
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import optuna

from explorer import __version__
from explorer.cost import candidate_cost, model_cost
from explorer.data import DEPTH_METRICS, MAYBE_WITHOUT_DEPTH, open_dataset, parse_data_spec, require_scores
from explorer.errors import UserError, refused_write
from explorer.processes import die_with_parent, held_between_trials, interrupted_once
from explorer.space import Candidate, SearchSpace, paper_candidate
from explorer.study import planning
from explorer.study.config import (  # noqa: F401
    BASELINES,
    DEFAULT_BASELINES,
    OBJECTIVES,
    SearchConfig,
    StudyContext,
    baseline_model,
    json_safe,
    objective_names,
    stored_config,
    study_context,
)
from explorer.study.finalists import (
    choose_finalists,
    finalist_trials,
    retrain_finalists,
)
from explorer.study.envelope import DEFAULT_NETWORKS, envelope_trials, train_envelope
from explorer.study.objective import Objective, hinted_if_asked
from explorer.study.planning import (
    MAX_SUPERNET_STEPS,
    RESERVE_S,
    STEP_GRID,
    Plan,
    TimeLimit,
    replan_finalists,
    replan_sampling,
    retrain_seconds,
    supernet_deadline,
)
from explorer.study.retry import (
    StopAfterTrials,
    counted_trials,
    guarded,
    resume_interrupted,
    set_objective_names,
)
from explorer.study._stopping import check_workers, ctrl_c_says_what_is_kept, end_workers, quiet_ctrl_c, study_kept
from explorer.study.records import record_study, record_values, study_record, trial_record
from explorer.study.run import SearchObserver, SearchRun
from explorer.study.sampling import RecentTrialsTPE
from explorer.study.storage import (
    local_url,
    open_storage,
    refused_leaves_nothing,
    searching_alone,
    study_dir,
)
from explorer.study.view import study_view
from explorer.supernet import default_path, load_supernet, read_supernet, train_supernet
from explorer.training.deployment import DeploymentData
from explorer.training.memory import release_host_memory
from explorer.training.train import resolve_accelerator


def make_sampler(config: SearchConfig, worker: int = 0) -> optuna.samplers.BaseSampler:
    seed = config.seed + 1000 * worker
    if config.sampler == "random":   # the yardstick the guided samplers must beat (bench_search_value)
        return optuna.samplers.RandomSampler(seed=seed)
    if len(config.objectives) > 1:
        return optuna.samplers.NSGAIISampler(seed=seed)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        # multivariate + group: the conditional LiDAR/ECU dimensions are modelled jointly; TPE reads the
        # best and the latest trials, so that an ask costs the same at trial 30,000 as at 600
        return RecentTrialsTPE(seed=seed, n_startup_trials=8, multivariate=True, group=True)


def make_pruner(config: SearchConfig) -> optuna.pruners.BasePruner:
    if not config.pruning or len(config.objectives) > 1:
        return optuna.pruners.NopPruner()
    # Early proxy losses rank candidates poorly: judge only in the second half of training, and
    # only prune the worst quarter (the baselines count towards the startup trials).
    return optuna.pruners.PercentilePruner(75.0, n_startup_trials=6,
                                           n_warmup_steps=max(config.train_steps // 2, 0))


def create_or_resume(context: StudyContext, storage: optuna.storages.BaseStorage) -> optuna.Study:
    """Creates the study (and enqueues the baselines, once) or resumes it after checking that its
    settings match. Only the process that creates the study enqueues, so concurrent starts on one
    database never duplicate the baselines."""
    config, space = context.config, context.space
    directions = ["minimize"] * len(config.objectives)
    try:
        study = optuna.create_study(study_name=config.study, storage=storage, directions=directions,
                                    sampler=make_sampler(config), pruner=make_pruner(config))
        created = True
    except optuna.exceptions.DuplicatedStudyError:
        study = optuna.load_study(study_name=config.study, storage=storage, sampler=make_sampler(config),
                                  pruner=make_pruner(config))
        created = False
    if created:
        record_study(study, config=config.to_dict(), explorer_version=__version__,
                     space_yaml=Path(space.source).read_text(), device_profile=context.device.to_dict(),
                     created=time.strftime("%Y-%m-%d %H:%M:%S"))
        if config.baselines:
            skipped = {}
            for name in config.baselines:
                model = baseline_model(name)
                if not isinstance(model, Candidate):
                    skipped[name] = ("a reference network, outside every space: it is compared after retraining "
                                     "(finalists) only")
                    continue
                if config.evaluator == "supernet" and not space.contains(model):
                    skipped[name] = (f"outside the space '{space.name}': the supernet cannot estimate it, so it "
                                     "is compared after retraining (finalists) only")
                    continue
                study.enqueue_trial({}, user_attrs=record_values(baseline=name))
            record_study(study, baselines_not_estimated=skipped)
        set_objective_names(study, objective_names(config))
    else:
        old = study_record(study).config
        if old:
            prev = SearchConfig.from_dict({**SearchConfig.defaults_of_older_studies(), **old})
            diff = [k for k in SearchConfig.IDENTITY if getattr(prev, k) != getattr(config, k)]
            if diff:
                k = diff[0]
                raise UserError(
                    f"study '{config.study}' was created with {k}={getattr(prev, k)!r}, not "
                    f"{getattr(config, k)!r}: resume with the same settings, pick another --study, or "
                    "use `explorer rescore` for another device or budget")
        study_context(study)   # its stored settings, space and device profile read: a damaged one before any trial
        set_objective_names(study, objective_names(config))  # studies made before objectives had names
    return study


@dataclass
class SearchOutcome:
    study: optuna.Study
    storage_url: str
    seconds: float
    interrupted_failed: int = 0
    retried: dict[int, int] = dataclasses.field(default_factory=dict)   # interrupted trial -> its retry
    not_retried: list[int] = dataclasses.field(default_factory=list)    # interrupted past --max-retries
    config: SearchConfig | None = None     # as run: a --time-limit plan may have sized its steps
    plan: "Plan | None" = None


class PhaseClock:
    """The wall time of a run's phases, in the order they ran: each lap ends where the next begins."""

    def __init__(self, started: float) -> None:
        self.last, self.seconds = started, {}

    def lap(self, phase: str) -> None:
        now = time.time()
        self.seconds[phase] = round(self.seconds.get(phase, 0.0) + now - self.last, 1)
        self.last = now


def run_worker(config_dict: dict, storage_url: str | None, n_trials: int | None, deadline: float | None,
               worker: int, reports: str, threads: int) -> None:
    """One worker process of a multi-process search (spawned): it dies with its parent (kill -9 too), and
    a Ctrl-C records its trial as interrupted (tried again) and ends it quietly."""
    die_with_parent()
    optuna.logging.set_verbosity(optuna.logging.WARNING)   # the parent speaks for the search
    try:
        with interrupted_once():
            _work(config_dict, storage_url, n_trials, deadline, worker, reports, threads)
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except Exception as exc:   # a full disk, a folder made read-only: the parent says it in one line
        if refused_write(exc) is None:
            raise
        raise SystemExit(2) from None


def _work(config_dict: dict, storage_url: str | None, n_trials: int | None, deadline: float | None,
          worker: int, reports: str, threads: int) -> None:
    import torch
    torch.set_num_threads(max(threads, 1))
    context = SearchConfig.from_dict(config_dict).resolve()   # this process's edge
    config = context.config
    storage = open_storage(storage_url, config.study, workers=2, reports=Path(reports), max_retries=config.max_retries)
    study = optuna.load_study(study_name=config.study, storage=storage, sampler=make_sampler(config, worker),
                              pruner=make_pruner(config))
    objective = Objective(context, study_dir(config.study, Path(reports)))
    _optimize(study, objective, n_trials, deadline)


def _optimize(study: optuna.Study, objective: Objective, n_trials: int | None, deadline: float | None,
              callbacks: list | None = None) -> None:
    cbs = list(callbacks or [])
    if n_trials is not None:
        # interrupted trials do not count (their retries do): see explorer.study.retry
        cbs.append(StopAfterTrials(n_trials))
        if counted_trials(study) >= n_trials:
            return
    timeout = None if deadline is None else max(deadline - time.time(), 0.0)
    if timeout is not None and timeout <= 0:
        return
    # everything loaded so far (torch, data, the evaluator's batches) lives as long as the worker:
    # frozen, no collection walks it. After a trial only the young generations are collected (what the
    # trial made): a full collection also walks the evaluator's stage memo and every stored trial, and
    # grows with the study
    gc.freeze()
    cbs.append(lambda _study, _trial: gc.collect(1))
    # a Ctrl-C stops the search between trials or at a training step's end, never in a storage write; a trial it
    # stops is not logged by Optuna (the search says it in one line)
    with quiet_ctrl_c(), held_between_trials() as asked:
        cbs.append(lambda study_, _trial: study_.stop() if asked() else None)
        study.optimize(guarded(objective, objective.config.max_retries, n_trials), timeout=timeout, callbacks=cbs,
                       catch=(Exception,), gc_after_trial=False)


def ensure_supernet(context: StudyContext, progress: Callable[[int, int, dict], None] | None = None,
                    data_progress: Callable[[int, int], None] | None = None,
                    deadline: float | None = None) -> Path | None:
    """The supernet file the study's evaluator reads: the given one (checked), or the cached one for
    (space, data, recipe), trained here first if it is missing or unfinished (until ``deadline`` at
    the latest: then it is left unfinished, to be finished by the next study with its recipe)."""
    config, space = context.config, context.space
    if config.evaluator != "supernet":
        return None
    if config.supernet:
        load_supernet(config.supernet, space)  # one clear line if it is foreign, corrupt or unfinished
        return Path(config.supernet)
    return train_supernet(space, config.data, config.supernet_recipe(), default_path(
        space, config.data, config.supernet_recipe()), resolve_accelerator(config.accelerator),
        progress=progress, data_progress=data_progress, deadline=deadline)


def _cached_supernet_steps(space: SearchSpace, config: SearchConfig) -> list[int]:
    """Step counts of the finished supernets cached for this space, data and recipe (steps aside)."""
    found = []
    for steps in sorted({*range(STEP_GRID, MAX_SUPERNET_STEPS + 1, STEP_GRID), config.supernet_steps}):
        path = default_path(space, config.data, dataclasses.replace(config.supernet_recipe(), steps=steps))
        try:
            if path.is_file() and read_supernet(path).get("complete"):
                found.append(steps)
        except UserError:
            continue  # a broken file is trained again in its place
    return found


def baseline_load(config: SearchConfig, speeds=None) -> float:
    """The baselines' retraining in paper designs' worth, for the time plan: each its measured training
    step over the paper design's (``speeds``), or without a measurement one for a candidate and for a
    reference network its MACs at the training size over the paper design's (which over-counts the
    ResNets)."""
    paper = candidate_cost(paper_candidate(), config.train_size).path_params_macs()[-1][1]
    load = 0.0
    for name in config.baselines:
        measured = speeds.relative_training(name) if speeds is not None else None
        model = baseline_model(name)
        if measured is not None:
            load += measured
        elif isinstance(model, Candidate):
            load += 1.0
        else:
            load += max(1.0, model_cost(model, config.train_size).path_params_macs()[-1][1] / paper)
    return load


def plan_search(context: StudyContext, storage: optuna.storages.BaseStorage, limit: "TimeLimit",
                sampling_s: float | None, on_data: Callable[[int, int], None] | None = None,
                clock: PhaseClock | None = None):
    """(config as it will run, plan, speeds): the data generated, the machine measured, the run sized
    to what is left of ``limit`` (see explorer.study.planning)."""
    config = context.config
    free = set(limit.free)
    old = stored_config(storage, config.study)   # a damaged one is one line before any work
    if old and "supernet_steps" in free and "supernet_steps" in old:
        config = dataclasses.replace(config, supernet_steps=int(old["supernet_steps"]))  # the study's supernet
        free.discard("supernet_steps")
    train_set = hinted_if_asked(config, open_dataset(config.data, "train", config.train_size, seed=config.seed,
                                                 progress=on_data), on_data)
    val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
    os.sync()  # data just generated is still being written back: steps measured meanwhile read slow
    if clock is not None:
        clock.lap("data")
    trains_supernet = config.evaluator == "supernet" and not config.supernet
    cached = _cached_supernet_steps(context.space, config) if trains_supernet else []
    must_measure_supernet = trains_supernet and ("supernet_steps" in free or config.supernet_steps not in cached)
    speeds = planning.measure_speeds(config, train_set, val_set, resolve_accelerator(config.accelerator),
                                     supernet=context.space if must_measure_supernet else None,
                                     baselines=_measured_baselines(config) if config.finalists else (),
                                     deployment=_deployment_data(config, train_set) if config.finalists else None)
    trial_s = 0.0 if config.evaluator == "supernet" else planning.SAFETY * (
        config.train_steps * speeds.retrain_step_s + speeds.retrain_eval_s)

    def plan(steps: int, steps_free: bool, is_cached: bool):
        return planning.plan_run(
            limit.remaining(), limit.seconds, speeds, sampling_s=sampling_s, supernet_steps=steps,
            supernet_free=steps_free, supernet_cached=is_cached or not trains_supernet,
            finalists=config.finalists, finalists_free="finalists" in free, finalist_steps=config.finalist_steps,
            finalist_steps_free="finalist_steps" in free,
            baselines=baseline_load(config, speeds), baseline_count=len(config.baselines), trial_s=trial_s)

    chosen = plan(config.supernet_steps, "supernet_steps" in free, config.supernet_steps in cached)
    larger = [s for s in cached if s >= chosen.supernet_steps]
    if "supernet_steps" in free and larger:  # a cached supernet at least as trained costs nothing
        chosen = plan(max(larger), False, True)
    config = dataclasses.replace(config, supernet_steps=chosen.supernet_steps, finalists=chosen.finalists,
                                 finalist_steps=chosen.finalist_steps)
    if config.evaluator != "supernet":   # the proxy evaluator trains every candidate: no supernet at all
        chosen = dataclasses.replace(chosen, supernet_steps=0)
    recipe = config.finalist_recipe()
    if recipe.tunes:
        chosen = dataclasses.replace(chosen, tune=f"{recipe.tune_steps} at {'x'.join(map(str, recipe.deploy_size))}")
    return config, chosen, speeds


def _measured_baselines(config: SearchConfig) -> tuple[str, ...]:
    """The baselines whose training is measured for the plan (the paper design's is the step itself)."""
    return tuple(n for n in config.baselines if baseline_model(n) != paper_candidate())


def _measure_again(config: SearchConfig, speeds, finalists: tuple[Candidate, ...] = ()):
    """The retraining speeds measured again, the ``finalists`` chosen by now with them (the supernet's
    is kept: it is trained by now)."""
    train_set = open_dataset(config.data, "train", config.train_size, seed=config.seed)
    val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
    fresh = planning.measure_speeds(config, train_set, val_set, resolve_accelerator(config.accelerator), supernet=False,
                                    baselines=_measured_baselines(config), finalists=finalists)
    return dataclasses.replace(fresh, supernet_step_s=speeds.supernet_step_s, tune_s=speeds.tune_s)


def _deployment_data(config: SearchConfig, train_set) -> DeploymentData:
    """The frames the finalists' tuning reads and is measured on, at the deployment size."""
    return DeploymentData(train_set, open_dataset(config.data, "train", config.input_size, seed=config.seed),
                          open_dataset(config.data, "val", config.input_size, train_augment=False))


def search(context: StudyContext, run: SearchRun = SearchRun(),
           observer: SearchObserver | None = None) -> SearchOutcome:
    """Runs (or resumes) the study ``context`` resolved until ``run.n_trials`` trials are done or
    ``run.timeout_s`` passes (the supernet's training and the finalists' retraining are not counted), then
    retrains the finalists, telling ``observer`` as it goes. With ``run.time_limit`` the whole run is sized
    to it first (explorer.study.planning): ``run.timeout_s`` is then the most sampling may take, and the
    time the finalists leave goes to the envelope's dedicated networks (:func:`_envelope_in_time_left`)."""
    config, observer = context.config, observer or SearchObserver()
    check_workers(run.workers)   # no more processes than the machine can run (cores, memory), in one line
    if parse_data_spec(config.data).kind in MAYBE_WITHOUT_DEPTH or config.metric not in DEPTH_METRICS:
        # data that cannot score a path by the study's metric is refused before the study exists
        require_scores(open_dataset(config.data, "val", config.train_size, train_augment=False), config.data,
                       config.metric, instead="score the paths by --metric photometric (a recording with its LiDAR), or ")
    if config.supernet:   # checked before the study's storage exists: a refused search creates nothing
        ensure_supernet(context)  # a foreign or corrupt file is one line before anything is measured
    url = run.storage_url or local_url(config.study, run.reports)
    started = run.time_limit.started if run.time_limit is not None else time.time()
    clock = PhaseClock(started)
    with refused_leaves_nothing(url, config.study), searching_alone(url, config.study), \
            ctrl_c_says_what_is_kept(url, config.study):
        outcome = _search(context, dataclasses.replace(run, storage_url=url), run.storage_url, observer, clock)
        runs = study_record(outcome.study).runs
        record_study(outcome.study, runs=runs + [{"started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)),
                                                  "seconds": round(time.time() - started, 1),
                                                  "phases": clock.seconds}])
    return outcome


def _search(context: StudyContext, run: SearchRun, given_url: str | None, observer: SearchObserver,
            clock: PhaseClock) -> SearchOutcome:
    """:func:`search`'s run, under the study's search lock (``run.storage_url`` is where the study is,
    ``given_url`` what the caller gave); ``clock`` is told where each phase ends. Each phase that changes
    the settings (the plan, the finalists' re-plan and retraining) hands the next one its context."""
    config, url, reports, time_limit = context.config, run.storage_url, run.reports, run.time_limit
    storage = open_storage(url, config.study, run.workers, reports, max_retries=config.max_retries)
    plan = speeds = None
    timeout_s = run.timeout_s
    wanted = (config.finalists, config.finalist_steps)   # before a plan shrinks them
    if time_limit is not None:
        config, plan, speeds = plan_search(context, storage, time_limit, run.timeout_s, observer.data, clock)
        context = context.with_config(config)
        clock.lap("measuring")
        timeout_s = plan.sampling_s
        observer.plan(plan)
    study = create_or_resume(context, storage)
    if plan is not None:
        record_study(study, plan=plan.to_dict())
    # No worker of this run has started yet; on local storage nobody else can be running: its RUNNING
    # trials were interrupted (kill -9), and are tried again. RDB storage does this by heartbeat.
    failed, retried, not_retried = 0, {}, []
    if given_url is None or given_url.startswith(("sqlite", "journal:")):
        failed, retried, not_retried = resume_interrupted(study, config.max_retries)
    if config.keep_weights:
        record_study(study, artifacts_dir=str((study_dir(config.study, reports) / "artifacts").resolve()))
    cutoff = None if plan is None else supernet_deadline(plan, time_limit, speeds, "paper" in config.baselines,
                                                         run.timeout_s)
    supernet = ensure_supernet(context, observer.supernet, observer.data, cutoff)   # the planned steps
    if supernet is not None:
        clock.lap("supernet")
        record_study(study, supernet=str(supernet.resolve()))
        plan = _note_unfinished(supernet, plan)
    if plan is not None:
        plan = replan_sampling(plan, time_limit.remaining(), run.timeout_s)
        timeout_s = plan.sampling_s
        _publish_plan(study, plan, observer)
    t0 = time.time()
    _sample(study, context, run, observer, None if timeout_s is None else t0 + timeout_s)
    clock.lap("sampling")
    if plan is not None and (config.finalists or config.baselines):
        config, plan = _replan_finalists(study, config, plan, speeds, time_limit, wanted, observer)
        context = context.with_config(config)
    if config.finalists:
        config, plan = _retrain_finalists(study, context, plan, time_limit, wanted, reports, observer, run.workers)
        clock.lap("finalists")
        if plan is not None:
            before, plan = plan, _envelope_in_time_left(study, config, plan, speeds, time_limit, reports, observer)
            if plan is not before:
                clock.lap("envelope")
    return SearchOutcome(study, url, time.time() - t0, failed, retried, not_retried, config, plan)


def _sample(study: optuna.Study, context: StudyContext, run: SearchRun, observer: SearchObserver,
            deadline: float | None) -> None:
    """Samples until ``run.n_trials`` or ``deadline``: in this process, or in ``run.workers`` processes."""
    config = context.config
    if run.workers != 1:
        _run_workers(study, config, run.storage_url, run.workers, run.n_trials, deadline, run.reports, observer)
        return
    release_host_memory()   # the measurements' and the supernet's training's pages, before the sampler's caches
    objective = Objective(context, study_dir(config.study, run.reports), observer.data)
    _optimize(study, objective, run.n_trials, deadline, [observer.trial])
    # the sampler's caches (the stage memo, the encoders' features) are not the retrainings': their
    # pages go back before those train at the deployment size (explorer.training.memory)
    del objective
    gc.unfreeze()
    release_host_memory()


def _retrained_and_skipped(study: optuna.Study, config: SearchConfig) -> tuple[int, int]:
    """(finalists retrained with the study's recipe, finalists and baselines asked for and not)."""
    recipe = config.finalist_recipe().to_dict()
    now = [trial_record(t) for t in finalist_trials(study) if trial_record(t).finalist.recipe == recipe]
    retrained = sum(1 for rec in now if not rec.baseline)
    return retrained, max(config.finalists - retrained, 0) + len(set(config.baselines) - {rec.baseline for rec in now})


def _envelope_in_time_left(study: optuna.Study, config: SearchConfig, plan: "Plan", speeds,
                           time_limit: "TimeLimit", reports: Path, observer: SearchObserver) -> "Plan":
    """Retrains the envelope's dedicated networks (``explorer envelope``'s, DEFAULT_NETWORKS of them) in
    the time the finalists left, each only if it ends before the time limit (the first by the plan's
    measure of one finalist, the others by the longest so far): a fast machine then gives the summary
    the envelope of the space instead of stopping early; a slow one starts none. Finalists and baselines
    come first: where the time limit stopped one of them, no time was left."""
    winner_retrained = any(not trial_record(t).baseline for t in finalist_trials(study))
    if not winner_retrained or _retrained_and_skipped(study, config)[1]:
        return plan
    before = len(envelope_trials(study))
    train_envelope(study_view(study), DEFAULT_NETWORKS, reports, deadline=time_limit.ends - RESERVE_S,
                   progress=observer.envelope, expected_s=retrain_seconds(speeds, 1, 0.0, config.finalist_steps))
    trained = len(envelope_trials(study)) - before
    if trained:
        plan = dataclasses.replace(plan, changes=plan.changes + (
            f"{trained} dedicated network(s) of the envelope retrained in the time the finalists left "
            "(explorer envelope adds more)",))
        _publish_plan(study, plan, observer)
    return plan


def _note_unfinished(supernet: Path, plan: "Plan | None") -> "Plan | None":
    """The plan, saying so when the time limit stopped the supernet short of its steps."""
    state = read_supernet(supernet)
    if plan is None or state.get("complete"):
        return plan
    why = "the machine ran slower than planned" if plan.fits else "the plan did not fit in the time limit"
    return dataclasses.replace(plan, changes=plan.changes + (
        f"supernet stopped at step {state['step']} of {state['recipe']['steps']}: {why}, and the rest of the "
        "run needed the time (its estimates are rougher; the next study with this recipe finishes it)",))


def _publish_plan(study: optuna.Study, plan: "Plan", observer: SearchObserver) -> None:
    """Records the plan as it stands now in the study, and tells the caller."""
    record_study(study, plan=plan.to_dict())
    observer.plan(plan)


def _run_workers(study: optuna.Study, config: SearchConfig, url: str, workers: int, n_trials: int | None,
                 deadline: float | None, reports: Path, observer: SearchObserver) -> None:
    """Samples in ``workers`` spawned processes sharing the study at ``url`` (the cores split among
    them), polling the study every 2 s until all have finished."""
    open_dataset(config.data, "val", config.train_size, progress=observer.data)  # generate once, not per worker
    if n_trials is not None:   # each worker starts one trial before it can count: no more workers than trials
        workers = max(1, min(workers, n_trials - counted_trials(study)))
    import multiprocessing as mp
    ctx = mp.get_context("spawn")
    threads = max(1, (os.cpu_count() or 1) // workers)
    procs = [ctx.Process(target=run_worker, args=(config.to_dict(), url, n_trials, deadline, i,
                                                  str(reports), threads))
             for i in range(workers)]
    for p in procs:
        p.start()
    finished = False
    try:
        while any(p.is_alive() for p in procs):
            time.sleep(2.0)
            observer.poll(study)
        finished = True
    finally:
        end_workers(procs, interrupted=not finished)   # a Ctrl-C here: each records its trial, then stops
    if any(p.exitcode == 2 for p in procs):
        raise UserError("a search worker could not write the study (a full disk, or a folder made read-only): free "
                        f"space there; {study_kept(url, config.study)}")


def _replan_finalists(study: optuna.Study, config: SearchConfig, plan: "Plan", speeds, time_limit: "TimeLimit",
                      wanted: tuple[int, int], observer: SearchObserver) -> tuple[SearchConfig, "Plan"]:
    """Sizes the finalists' retraining to what is left of ``time_limit`` once sampling is over:
    (config with the finalists and steps that fit, the plan as re-made)."""
    done = [trial_record(t).finalist.recipe["steps"] for t in finalist_trials(study)]
    steps_free = "finalist_steps" in time_limit.free and not done   # a resumed study keeps its recipe
    # the machine may be busier or freer than when it was first measured, and the finalists are known
    # now: measure it again, on them (seconds)
    count = max(config.finalists, wanted[0]) if "finalists" in time_limit.free else config.finalists
    chosen = tuple(Candidate.from_dict(trial_record(t).candidate) for t in choose_finalists(study, count))
    speeds = _measure_again(config, speeds, chosen)
    plan = replan_finalists(plan, time_limit.remaining(), speeds, baseline_load(config, speeds),
                            steps_free=steps_free, finalists_free="finalists" in time_limit.free,
                            baseline_count=len(config.baselines), wanted=wanted)
    config = dataclasses.replace(config, finalists=plan.finalists,
                                 finalist_steps=plan.finalist_steps if steps_free or not done else max(done))
    # the best finalist and the paper design are retrained whatever the time, once started: when even
    # they no longer fit, none is (a winner retrained alone could not be compared)
    must_s = retrain_seconds(speeds, 1, 1.0 if "paper" in config.baselines else 0.0, config.finalist_steps)
    left = time_limit.remaining() - RESERVE_S
    if config.finalists and not done and must_s > left:
        needed = "the best one and the paper design need" if "paper" in config.baselines else "the best one needs"
        plan = dataclasses.replace(plan, finalists=0, retrain_jobs=0, retrain_s=0.0, changes=plan.changes + (
            f"no finalist retrained: {needed} about {must_s / 60:.1f} min at "
            f"{config.finalist_steps} steps on this machine now, {max(left, 0) / 60:.1f} min are left: the winner "
            "is the search's best estimate, not retrained (give a longer --time-limit)",))
        config = dataclasses.replace(config, finalists=0)
    _publish_plan(study, plan, observer)
    return config, plan


def _retrain_finalists(study: optuna.Study, context: StudyContext, plan: "Plan | None",
                       time_limit: "TimeLimit | None", wanted: tuple[int, int], reports: Path,
                       observer: SearchObserver, workers: int = 1) -> tuple[SearchConfig, "Plan | None"]:
    """Retrains the finalists and the baselines (``workers`` at once, or one per GPU); (config, plan)
    counting the finalists retrained."""
    config = context.config
    # the re-plan stood on a few steps' measurement: finalists it dropped are retrained after the
    # others when the time those took says they still fit
    extra, deadline = 0, None
    if plan is not None:   # the time limit holds even when the machine slowed after planning
        extra = max(wanted[0] - config.finalists, 0) if "finalists" in time_limit.free else 0
        deadline = time_limit.ends - RESERVE_S
    left_s = deadline - time.time() if deadline is not None else math.inf
    retrain_finalists(study, context, reports, progress=observer.finalist, extra=extra, deadline=deadline,
                      workers=workers)
    retrained, skipped = _retrained_and_skipped(study, config)
    if plan is not None and skipped:
        plan = dataclasses.replace(plan, not_retrained=skipped,
                                   changes=plan.changes + (planning.not_retrained(skipped, plan, left_s),))
        _publish_plan(study, plan, observer)
    if plan is not None and retrained > plan.finalists:
        plan = dataclasses.replace(plan, finalists=retrained, retrain_jobs=plan.retrain_jobs + retrained - plan.finalists,
                                   changes=plan.changes + (
            f"{retrained - plan.finalists} more finalist(s) retrained: the others took less than planned",))
        config = dataclasses.replace(config, finalists=retrained)
        _publish_plan(study, plan, observer)
    return config, plan
