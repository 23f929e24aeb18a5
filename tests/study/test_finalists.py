import optuna
import pytest
import torch

from conftest import TINY_DATA
from explorer.study.finalists import choose_finalists, estimate_trials, finalist_trials, retrain_finalists
from explorer.study.results import baseline_trial, best_trial, finalists_frame, is_retrained, winner
from explorer.study.search import SearchConfig, SearchObserver, SearchRun, search
from explorer.study.view import study_view
from explorer.space import Candidate
from explorer.training.train import evaluate, save_checkpoint

CFG = SearchConfig(study="fin", space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), batch_size=8,
                   val_limit=8, evaluator="supernet", supernet_steps=4, finalists=2, finalist_steps=5,
                   tune_steps=2)


class Plans(SearchObserver):
    """Keeps every plan the search tells (at the start, and at each re-plan) in ``seen``."""

    def __init__(self, seen: list) -> None:
        self.seen = seen

    def plan(self, plan) -> None:
        self.seen.append(plan)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    reports = tmp_path_factory.mktemp("fin")
    return search(CFG.resolve(), SearchRun(n_trials=6, timeout_s=None, reports=reports)), reports


@pytest.mark.slow
def test_best_candidates_and_baselines_are_retrained(finished):
    out, _ = finished
    fin = finalist_trials(out.study)
    labels = sorted(t.user_attrs.get("baseline", "") for t in fin)
    assert labels == ["", "", "fastdepth", "paper", "paper-nee"]
    picked = {t.user_attrs["candidate_key"] for t in fin if not t.user_attrs.get("baseline")}
    estimates = sorted((t for t in out.study.trials if t.state == optuna.trial.TrialState.COMPLETE
                        and not is_retrained(t) and not t.user_attrs.get("baseline")), key=lambda t: t.values[0])
    first = estimates[0]
    other = [t for t in estimates if t.user_attrs["candidate"]["encoder_blocks"] != first.user_attrs["candidate"]["encoder_blocks"]]
    runner_up = other[0] if other else next(t for t in estimates if t.user_attrs["candidate_key"] != first.user_attrs["candidate_key"])
    # the best estimate, then the best of the other encoder
    assert picked == {first.user_attrs["candidate_key"], runner_up.user_attrs["candidate_key"]}
    for t in fin:
        assert t.user_attrs["train"]["steps"] == 5 + 2 and "weights_artifact" in t.user_attrs
        # trained at 32x32, tuned and measured at the deployment size, on named frames
        assert t.user_attrs["measured"] == {"data": TINY_DATA, "split": "val", "frames": 8, "input_size": [64, 64]}
        assert t.params == {}                                    # samplers never learn from them
    win = winner(out.study)
    assert is_retrained(win) and win.values[0] == min(t.values[0] for t in fin if not t.user_attrs.get("baseline"))
    assert best_trial(out.study) is not None and not is_retrained(best_trial(out.study))
    assert baseline_trial(out.study, "paper", retrained=True) is not None
    frame = finalists_frame(out.study)
    assert len(frame) == 5 and frame["estimated"].notna().sum() == 2   # baselines outside the space: no estimate


def test_finalists_spread_over_image_encoders():
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())

    def add(value, blocks, width, key, baseline=None):
        cand = {"encoder_blocks": blocks, "width_mult": width}
        attrs = {"candidate": cand, "candidate_key": key, "path_metrics": [], "workloads": {}}
        study.add_trial(optuna.trial.create_trial(values=[value], user_attrs={**attrs, **({"baseline": baseline} if baseline else {})}))

    add(0.29, 9, 1.0, "paper", baseline="paper")   # baselines are never finalists
    add(0.30, 9, 1.0, "a")
    add(0.30, 9, 1.0, "a")                          # a repeated candidate counts once
    add(0.301, 9, 1.0, "b")
    add(0.31, 7, 1.0, "c")
    add(0.32, 6, 1.0, "d")
    add(0.33, 6, 0.5, "e")
    keys = lambda n: [t.user_attrs["candidate_key"] for t in choose_finalists(study, n)]  # noqa: E731
    assert keys(1) == ["a"]
    assert keys(3) == ["a", "c", "d"]               # one per encoder before a second of any
    assert keys(5) == ["a", "c", "d", "e", "b"]     # then the next best, whatever the encoder
    assert keys(9) == ["a", "c", "d", "e", "b"]


def test_a_finished_finalist_is_never_redone(finished):
    out, reports = finished
    before = len(out.study.trials)
    again = search(CFG.resolve(), SearchRun(n_trials=6, timeout_s=None, reports=reports))
    assert len(again.study.trials) == before


def test_an_interrupted_retraining_resumes_from_its_checkpoint(finished, tmp_path):
    import dataclasses
    from explorer.data import open_dataset
    from explorer.model import build_network
    out, _ = finished
    cfg = dataclasses.replace(CFG, study="fin2", baselines=False, finalists=1)
    fresh = optuna.create_study(study_name="fin2", storage=optuna.storages.InMemoryStorage())
    fresh.set_user_attr("config", cfg.to_dict())
    for t in out.study.trials:
        if t.state == optuna.trial.TrialState.COMPLETE and not is_retrained(t):
            fresh.add_trial(t)
    cand = Candidate.from_dict(best_trial(fresh).user_attrs["candidate"])
    # a kill after the tuning's last step, before its trial was stored: both phases' checkpoints hold
    # finished weights
    recipe = cfg.finalist_recipe()
    torch.manual_seed(123)
    net = build_network(cand)
    ckpt = tmp_path / "fin2" / "finalists" / f"{cand.key}.pt"
    save_checkpoint(ckpt, net, recipe.train, recipe.train.steps, torch.optim.AdamW(net.parameters()))
    save_checkpoint(ckpt.with_name(f"{cand.key}-tune.pt"), net, recipe.tune_config(), recipe.tune_steps,
                    torch.optim.AdamW(net.parameters()))
    # measured at the deployment size
    expected = evaluate(net, open_dataset(TINY_DATA, "val", (64, 64), train_augment=False), limit=8)
    retrain_finalists(fresh, cfg.resolve(), tmp_path)
    done = finalist_trials(fresh)
    assert [t.user_attrs["candidate_key"] for t in done] == [cand.key]
    # nothing was trained again: the metrics are those of the checkpoint's weights
    assert done[0].user_attrs["path_metrics"][-1]["rmse"] == pytest.approx(expected["rmse"].iloc[-1], rel=1e-5)
    assert not ckpt.exists()                                     # removed once its trial is stored


def test_finalists_a_replan_dropped_are_retrained_when_the_others_leave_time(finished, tmp_path):
    import dataclasses
    import time
    out, _ = finished
    cfg = dataclasses.replace(CFG, study="fin3", baselines=False, finalists=1)

    def study_of_estimates(name):
        s = optuna.create_study(study_name=name, storage=optuna.storages.InMemoryStorage())
        for t in out.study.trials:
            if t.state == optuna.trial.TrialState.COMPLETE and not is_retrained(t):
                s.add_trial(t)
        return s

    said = []
    roomy = study_of_estimates("fin3")
    retrain_finalists(roomy, cfg.resolve(), tmp_path, extra=1, deadline=time.time() + 600,
                      progress=lambda i, n, what: said.append(what))
    wanted = [t.user_attrs["candidate_key"] for t in choose_finalists(roomy, 2)]
    assert [t.user_attrs["candidate_key"] for t in finalist_trials(roomy)] == wanted   # the planned one first
    # a deadline the first finalist's time says cannot be met: only the planned one
    tight = study_of_estimates("fin4")
    retrain_finalists(tight, dataclasses.replace(cfg, study="fin4").resolve(), tmp_path, extra=1, deadline=time.time(),
                      progress=lambda i, n, what: said.append(what))
    assert [t.user_attrs["candidate_key"] for t in finalist_trials(tight)] == wanted[:1]
    assert any(what.startswith("no time for") for what in said)


@pytest.mark.slow
def test_a_time_limit_measures_the_machine_and_records_its_plan(tmp_path):
    import dataclasses
    from explorer.study.planning import TimeLimit
    seen = []
    limit = TimeLimit(600.0, free=frozenset({"finalists", "finalist_steps"}))
    out = search(dataclasses.replace(CFG, study="roomy").resolve(),
                 SearchRun(n_trials=3, timeout_s=None, reports=tmp_path, time_limit=limit), Plans(seen))
    plan = out.study.user_attrs["plan"]
    assert seen and seen[-1].to_dict() == plan      # told at the start and at each re-plan; the last one stored
    assert plan["supernet_steps"] == CFG.supernet_steps and plan["sampling_s"] > 0
    assert (out.config.finalists, out.config.finalist_steps) == (2, 5)      # time enough: as asked
    assert len([t for t in finalist_trials(out.study) if not t.user_attrs.get("baseline")]) == 2
    # the run's wall time, phase by phase in the order they ran, adds up to the whole run
    run = out.study.user_attrs["runs"][-1]
    assert list(run["phases"]) == ["data", "measuring", "supernet", "sampling", "finalists", "envelope"]
    assert sum(run["phases"].values()) == pytest.approx(run["seconds"], abs=0.5)
    assert run["phases"]["finalists"] > 0 and run["phases"]["measuring"] > 0
    # the time the finalists left went to the envelope's dedicated networks, at the winner's recipe
    from explorer.study.envelope import envelope, envelope_trials
    made = envelope_trials(out.study)
    assert 1 <= len(made) <= 4 and any(c.startswith(f"{len(made)} dedicated network(s) of the envelope")
                                       for c in plan["changes"])
    assert all(t.user_attrs["envelope"]["recipe"]["steps"] == 5 for t in made)
    assert envelope(study_view(out.study)).ratio is not None
    from explorer.report import write_report
    html = write_report(study_view(out.study), out_dir=tmp_path / "report").read_text()
    assert 'id="plan"' in html and "supernet 4 steps" in html and "2 finalist(s) retrained 5 steps" in html
    assert "measuring 0." in html and "finalists " in html   # the wall time row names the phases
    assert 'id="envelope-ratio"' in html and 'id="envelope-hint"' not in html


@pytest.mark.slow
def test_no_dedicated_network_starts_that_would_end_after_the_deadline(finished):
    """The first network's time is the caller's measure (``expected_s``), the others' the longest so far."""
    import time

    from explorer.study.envelope import envelope_trials, train_envelope
    out, reports = finished
    before, said = len(envelope_trials(out.study)), []
    train_envelope(study_view(out.study), 2, reports, deadline=time.time() + 5, expected_s=60.0,
                   progress=lambda i, n, what: said.append(what))
    assert len(envelope_trials(out.study)) == before and any(what.startswith("no time for") for what in said)


@pytest.mark.slow
def test_the_envelope_gets_no_time_where_the_time_limit_stopped_a_finalist(finished, tmp_path):
    """Finalists and baselines come first: a search whose time limit stopped one of them starts no
    dedicated network of the envelope, however much time the plan's measure says is left."""
    import dataclasses

    from explorer.study.envelope import envelope_trials
    from explorer.study.planning import Plan, Speeds, TimeLimit
    from explorer.study.search import _envelope_in_time_left
    out, _ = finished
    study = optuna.create_study(study_name="copy", storage=optuna.storages.InMemoryStorage())
    for key, value in out.study.user_attrs.items():
        study.set_user_attr(key, value)
    study.add_trials(out.study.get_trials(deepcopy=True))
    plan = Plan(limit_s=3600, supernet_steps=0, supernet_s=0, sampling_s=0, finalists=out.config.finalists,
                finalist_steps=out.config.finalist_steps, retrain_jobs=0, retrain_s=0)
    speeds, limit = Speeds(retrain_step_s=0.01, retrain_eval_s=0.1, supernet_step_s=0), TimeLimit(3600)
    before = len(envelope_trials(study))
    one_more = dataclasses.replace(out.config, finalists=out.config.finalists + 1)   # one the limit stopped
    assert _envelope_in_time_left(study, one_more, plan, speeds, limit, tmp_path, SearchObserver()) is plan
    assert len(envelope_trials(study)) == before
    as_asked = _envelope_in_time_left(study, out.config, plan, speeds, limit, tmp_path, SearchObserver())
    assert len(envelope_trials(study)) > before and "dedicated network(s) of the envelope" in as_asked.changes[-1]


@pytest.mark.slow
def test_a_time_limit_too_short_for_any_retraining_retrains_none_and_says_so(tmp_path):
    import dataclasses
    from explorer.study.planning import TimeLimit
    out = search(dataclasses.replace(CFG, study="tight").resolve(),
                 SearchRun(n_trials=3, timeout_s=None, reports=tmp_path,
                           time_limit=TimeLimit(1.0, free=frozenset({"finalists", "finalist_steps"}))))
    assert out.config.finalists == 0 and out.config.finalist_steps == 5   # never more steps than asked
    changes = out.study.user_attrs["plan"]["changes"]
    assert any(c.startswith("no finalist retrained") and "longer --time-limit" in c for c in changes)
    assert finalist_trials(out.study) == []


@pytest.mark.slow
def test_a_reference_network_joins_the_study_as_a_baseline(tmp_path):
    import dataclasses
    from explorer.cost import profile_reference
    from explorer.report import write_report
    from explorer.study.results import missing_baselines, rescore, trials_frame
    cfg = dataclasses.replace(CFG, study="refs", baselines=("paper", "fastdepth-pruned"), finalists=1)
    out = search(cfg.resolve(), SearchRun(n_trials=3, timeout_s=None, reports=tmp_path))
    study = out.study
    assert "fastdepth-pruned" in study.user_attrs["baselines_not_estimated"]   # outside every space
    ref = baseline_trial(study, "fastdepth-pruned", retrained=True)
    assert ref is not None and ref.user_attrs["reference"] == "fastdepth-pruned" and "candidate" not in ref.user_attrs
    assert len(ref.user_attrs["path_metrics"]) == 2                            # the scan, then the network
    expected = profile_reference("fastdepth-pruned", (64, 64), "tx2")["latency_ms"].iloc[0]
    assert ref.user_attrs["latency_ms"] == pytest.approx([0.0, expected])
    assert {t.user_attrs.get("baseline", "") for t in finalist_trials(study)} == {"", "paper", "fastdepth-pruned"}
    assert missing_baselines(study_view(study)) == []                                    # paper-nee was not asked for
    assert "FastDepth after NetAdapt" in trials_frame(study).set_index("number").loc[ref.number, "architecture"]
    again = rescore(study, "rpi4", ["time:uniform:100ms"])
    assert "fastdepth-pruned" in set(again["baseline"])
    html = write_report(study_view(study), out_dir=tmp_path / "report").read_text()
    table2 = html.split('<section id="table2">')[1].split("</section>")[0]
    assert "fastdepth-pruned" in table2 and "paper design" in table2


def test_a_baseline_that_beats_every_retrained_candidate_is_named():
    from explorer.study.results import unbeaten_baseline
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    attrs = {"candidate": {}, "path_metrics": [], "workloads": {}}

    def add(value, key, **extra):
        study.add_trial(optuna.trial.create_trial(values=[value], user_attrs={**attrs, "candidate_key": key, **extra}))

    add(0.30, "a")                                                  # the search's estimate
    add(0.35, "a", finalist={"estimate_trial": 0, "recipe": {}})                   # retrained: worse than estimated
    add(0.33, "paper", baseline="paper", finalist={"recipe": {}})                # the paper design, retrained
    assert unbeaten_baseline(study).user_attrs["baseline"] == "paper"
    add(0.32, "b", finalist={"estimate_trial": 0, "recipe": {}})                   # a candidate that beats it
    assert unbeaten_baseline(study) is None


def test_a_deadline_keeps_the_best_finalist_and_the_paper_design_and_drops_the_rest(tmp_path, monkeypatch):
    """A machine that slowed after planning: the jobs that no longer fit before the time limit are left
    out, last ones first, but the study still has its best finalist and the paper design to compare."""
    import dataclasses
    import time
    import explorer.study.finalists as finalists
    from explorer.space import SearchSpace
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    space = SearchSpace.from_yaml("tiny")
    for i, cand in enumerate(space.enumerate()):
        if i == 4:
            break
        study.add_trial(optuna.trial.create_trial(values=[0.3 + i / 100], user_attrs={
            "candidate": cand.to_dict(), "candidate_key": cand.key, "path_metrics": [], "workloads": {}}))
    retrained = []
    monkeypatch.setattr(finalists, "Objective", lambda *a, **k: None)
    monkeypatch.setattr(finalists, "train_finalist", lambda obj, job, **k: (
        time.sleep(0.05), retrained.append(job.baseline or job.model().key)))
    monkeypatch.setattr(finalists, "_store", lambda study, artifacts, result: None)
    config = dataclasses.replace(CFG, finalists=3, baselines=("fastdepth", "paper", "paper-nee"))
    retrain_finalists(study, config.resolve(), tmp_path, deadline=time.time() + 0.12)
    best = choose_finalists(study, 1)[0].user_attrs["candidate_key"]
    assert retrained[:2] == [best, "paper"]                  # whatever the time
    assert 2 <= len(retrained) < 6                           # the rest only while they fit
    retrained.clear()
    retrain_finalists(study, config.resolve(), tmp_path, deadline=None)
    assert len(retrained) == 6                               # no time limit: every job


@pytest.mark.slow
def test_finalists_retrained_by_two_workers_match_one_process(finished, tmp_path):
    """Two worker processes retrain the same jobs as one process, with the same results (each job
    seeded alike); only this process writes the study."""
    import dataclasses
    out, _ = finished
    cfg = dataclasses.replace(CFG, study="par", baselines=("paper",), finalists=2)

    def study_of_estimates():
        s = optuna.create_study(study_name="par", storage=optuna.storages.InMemoryStorage())
        for t in out.study.trials:
            if t.state == optuna.trial.TrialState.COMPLETE and not is_retrained(t):
                s.add_trial(t)
        return s

    one, two = study_of_estimates(), study_of_estimates()
    retrain_finalists(one, cfg.resolve(), tmp_path / "one")
    said = []
    retrain_finalists(two, cfg.resolve(), tmp_path / "two", workers=2, progress=lambda i, n, what: said.append(what))
    key = lambda t: (t.user_attrs["candidate_key"], t.user_attrs.get("baseline", ""))   # noqa: E731
    a, b = sorted(finalist_trials(one), key=key), sorted(finalist_trials(two), key=key)
    assert [key(t) for t in a] == [key(t) for t in b] and len(a) == 3
    for x, y in zip(a, b):
        assert y.values[0] == pytest.approx(x.values[0], rel=1e-3)
        assert "weights_artifact" in y.user_attrs
    assert said[-1] == "finalists retrained" and sum(w.startswith("retraining") for w in said) == 3
    assert not list((tmp_path / "two" / "par" / "finalists").glob("*.pt"))   # checkpoints gone once stored


@pytest.mark.slow
def test_a_supernet_the_time_limit_stopped_still_serves_the_study(tmp_path, monkeypatch):
    import dataclasses
    import time
    import explorer.study.search as search_module
    from explorer.study.planning import TimeLimit
    monkeypatch.setattr(search_module, "supernet_deadline", lambda *a, **k: time.time())   # the machine slowed
    out = search(dataclasses.replace(CFG, study="cut", supernet_steps=300, baselines=("paper",), finalists=1).resolve(),
                 SearchRun(n_trials=3, timeout_s=None, reports=tmp_path, time_limit=TimeLimit(600.0, free=frozenset())))
    changes = out.study.user_attrs["plan"]["changes"]
    assert any(c.startswith("supernet stopped at step") and "of 300" in c for c in changes)
    estimates = estimate_trials(out.study)
    assert estimates and all(t.user_attrs["evaluator"]["evaluator"] == "supernet" for t in estimates)
    assert finalist_trials(out.study)


@pytest.mark.parametrize("step_s, retrained", [(0.01, 1), (30.0, 0)])
def test_when_even_the_best_finalist_and_the_paper_design_no_longer_fit_none_is_retrained(monkeypatch, step_s,
                                                                                          retrained):
    """The machine slowed after planning so much that the two retrainings a comparison needs would
    overrun the time limit: none starts, and the plan says why."""
    import dataclasses
    import explorer.study.search as search_module
    from explorer.space import SearchSpace
    from explorer.study.planning import Plan, Speeds, TimeLimit
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    cand = next(iter(SearchSpace.from_yaml("tiny").enumerate()))
    study.add_trial(optuna.trial.create_trial(values=[0.3], user_attrs={
        "candidate": cand.to_dict(), "candidate_key": cand.key, "path_metrics": [], "workloads": {}}))
    speeds = Speeds(retrain_step_s=step_s, retrain_eval_s=0.1, supernet_step_s=0.0, finalist_step_s=(step_s,))
    monkeypatch.setattr(search_module, "_measure_again", lambda config, speeds, chosen: speeds)
    config = dataclasses.replace(CFG, finalists=1, finalist_steps=150, baselines=("paper",))
    planned = Plan(limit_s=600.0, supernet_steps=0, supernet_s=0.0, sampling_s=60.0, finalists=1, finalist_steps=150,
                   retrain_jobs=2, retrain_s=10.0)
    limit = TimeLimit(600.0, started=__import__("time").time() - 300.0, free=frozenset())
    config, plan = search_module._replan_finalists(study, config, planned, speeds, limit, (1, 150), SearchObserver())
    assert config.finalists == plan.finalists == retrained
    assert any(c.startswith("no finalist retrained") for c in plan.changes) == (retrained == 0)
    if not retrained:   # a study without baselines is not told of a paper design it does not have
        assert any("the best one and the paper design need" in c for c in plan.changes)
        alone = dataclasses.replace(config, finalists=1, baselines=())
        _, plan = search_module._replan_finalists(study, alone, planned, speeds, limit, (1, 150), SearchObserver())
        said = [c for c in plan.changes if c.startswith("no finalist retrained")]
        assert said and "paper" not in said[0] and "the best one needs" in said[0]


@pytest.mark.slow
def test_the_exported_winner_measures_what_the_study_reported(finished, tmp_path, capsys):
    """Trained at 32x32, deployed at 64x64: the study's figures for its winner and the paper design are
    those of the exported graphs at 64x64 on the same frames (another size: tests/cli/test_cli.py)."""
    from explorer.anytime import anytime_loss
    from explorer.study.export import export_from_study
    out, reports = finished
    for trial in (winner(out.study), baseline_trial(out.study, "paper", retrained=True)):
        manifest = export_from_study("fin", trial.number, tmp_path / f"t{trial.number}", None, reports)
        assert manifest.measured.model_dump(mode="json") == {**trial.user_attrs["measured"],
                                                             "by": "onnxruntime, the exported graphs"}
        assert manifest.input_size == manifest.tuned_size == (64, 64)
        exported = [p["rmse"] for p in manifest.path_metrics]
        assert exported == pytest.approx([p["rmse"] for p in trial.user_attrs["path_metrics"]], abs=0.01)
        assert manifest.source.study_path_metrics == trial.user_attrs["path_metrics"]
        costs = [c for c in manifest.expected_cost["tx2"].latency_ms]
        assert anytime_loss(costs, exported, "time:uniform:33ms") == pytest.approx(trial.values[0], abs=0.01)


@pytest.mark.slow
def test_the_envelope_of_dedicated_networks(finished, run_cli):
    """Dedicated networks (single-exit twins of the search's candidates, or candidates trained for an
    earlier path alone), retrained with the finalists' recipe and measured at
    the deployment size, never count as estimates or finalists; the envelope serves each budget with the
    best of them ready by it, and the winner is compared with it."""
    from explorer.anytime import anytime_loss
    from explorer.report import write_report
    from explorer.study.envelope import dedicated, envelope, envelope_summary, envelope_trials
    out, reports = finished
    before_winner = winner(out.study).number
    if not envelope_trials(out.study):    # before: the summary and the report say how to get it
        assert "explorer envelope --study fin" in envelope_summary(study_view(out.study))
        before = write_report(study_view(out.study), out_dir=reports / "before-envelope").read_text()
        assert 'id="envelope-hint"' in before and "explorer envelope --study fin" in before
        shared = "postgresql://me:secret@db.lab/studies"     # a study elsewhere: the command says where
        assert "--storage postgresql://me:***@db.lab/studies" in envelope_summary(study_view(out.study), shared)
        html = write_report(study_view(out.study), out_dir=reports / "shared", storage_url=shared).read_text()
        assert "--storage postgresql://me:***@db.lab/studies" in html and "secret" not in html
    code, text, err = run_cli("envelope", "--study", "fin", "--networks", "1", "--reports", reports)
    assert code == 0, err
    made = envelope_trials(out.study)
    assert len(made) == 1
    for t in made:
        cand, path = Candidate.from_dict(t.user_attrs["candidate"]), t.user_attrs["envelope"]["path"]
        # a single-exit twin, or a candidate trained for one of its earlier paths alone
        assert (cand == dedicated(cand) and path == 1) or 1 <= path < cand.num_paths - 1
        assert t.user_attrs["measured"]["input_size"] == [64, 64]
    assert winner(out.study).number == before_winner                     # never a finalist
    assert not {t.number for t in made} & {t.number for t in estimate_trials(out.study)}
    found = envelope(study_view(out.study))
    assert found.costs[0] == 0 and all(a < b for a, b in zip(found.costs, found.costs[1:]))
    assert all(a > b for a, b in zip(found.errors, found.errors[1:]))  # each step serves budgets better
    assert found.loss == pytest.approx(anytime_loss(found.costs, found.errors, "time:uniform:33ms"))
    assert found.ratio == pytest.approx(winner(out.study).values[0] / found.loss)
    assert "x the envelope" in " ".join(text.split())
    assert f"{found.ratio:.3f} x the envelope of" in envelope_summary(study_view(out.study))
    html = (reports / "fin" / "report.html").read_text()          # the command brought the report up to date
    assert 'id="envelope-ratio"' in html and f"{found.ratio:.3f}" in html and 'id="envelope-hint"' not in html
    assert "explorer envelope" not in envelope_summary(study_view(out.study))
    code, _, _ = run_cli("envelope", "--study", "fin", "--networks", "1", "--reports", reports)   # cached
    assert code == 0 and len(envelope_trials(out.study)) == len(made)


def test_finalists_retrained_beyond_the_plan_are_counted_as_finalists_not_baselines(monkeypatch, tmp_path):
    """The finalists' time said one more fitted than planned: the plan counts it among the finalists,
    and its baselines stay those the study has (not one fewer)."""
    import dataclasses
    import types
    import explorer.study.search as search_module
    from explorer.study.planning import Plan, TimeLimit
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    monkeypatch.setattr(search_module, "retrain_finalists", lambda *args, **kwargs: [])
    monkeypatch.setattr(search_module, "_retrained_and_skipped", lambda study, config: (2, 0))
    config = dataclasses.replace(CFG, finalists=1, finalist_steps=150, baselines=("paper",))
    planned = Plan(limit_s=600.0, supernet_steps=4, supernet_s=0.0, sampling_s=60.0, finalists=1, finalist_steps=150,
                   retrain_jobs=2, retrain_s=10.0)
    limit = TimeLimit(600.0, free=frozenset({"finalists"}))
    config, plan = search_module._retrain_finalists(study, types.SimpleNamespace(config=config), planned, limit,
                                                    (3, 150), tmp_path, SearchObserver())
    assert (config.finalists, plan.finalists, plan.retrain_jobs) == (2, 2, 3)
    assert "2 finalist(s) and 1 baseline(s) retrained" in plan.describe()
    assert plan.changes[-1].startswith("1 more finalist(s) retrained")


@pytest.mark.slow
def test_a_time_limited_proxy_search_plans_no_supernet(tmp_path):
    """With the proxy evaluator every candidate trains alone: the plan, its line and the report say
    there is no supernet, and none is trained."""
    import dataclasses
    from explorer.report import write_report
    from explorer.study.planning import Plan, TimeLimit
    cfg = dataclasses.replace(CFG, study="proxy-plan", evaluator="proxy", train_steps=3, finalists=1, baselines=())
    seen = []
    out = search(cfg.resolve(), SearchRun(n_trials=2, timeout_s=None, reports=tmp_path,
                                          time_limit=TimeLimit(600.0, free=frozenset({"finalists", "finalist_steps"}))),
                 Plans(seen))
    plan = out.study.user_attrs["plan"]
    assert plan["supernet_steps"] == 0 and plan["supernet_s"] == 0
    assert seen and all(p.supernet_steps == 0 for p in seen)
    line = Plan(**{**plan, "changes": tuple(plan["changes"])}).describe()
    assert "no supernet" in line and "supernet 4 steps" not in line
    html = write_report(study_view(out.study), out_dir=tmp_path / "report").read_text()
    assert 'id="plan"' in html and "no supernet" in html and "supernet 4 steps" not in html
    assert "phases" in out.study.user_attrs["runs"][-1]
    assert finalist_trials(out.study)
