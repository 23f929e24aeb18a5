"""Every trial is scored as the network that ships: its exits no better than an earlier path left out,
its costs and per-path figures those of what ships, unless --keep-every-exit."""

import json
from pathlib import Path

import numpy as np
import optuna
import pandas as pd
import pytest
import torch
import yaml
from PIL import Image

import explorer
from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost
from explorer.deploy import export as export_module
from explorer.deploy.manifest import read_manifest
from explorer.model import build_network
from explorer.model.shipped import exit_names
from explorer.space import Candidate
from explorer.study import objective as objective_module
from explorer.study.objective import Objective
from explorer.study.records import trial_record
from explorer.study.results import trial_anytime_loss
from explorer.study.run import SearchRun
from explorer.study.search import SearchConfig, search
from explorer.supernet.evaluators import Evaluation
from explorer.training.train import TrainConfig, save_checkpoint
from conftest import TINY_DATA

SPACES = Path(explorer.__file__).parent / "search_spaces"

TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=2,
            batch_size=8, val_limit=16, evaluator="proxy", finalists=0, baselines=(), pruning=False,
            keep_weights=False)


class WorseSecondPath:
    """An evaluator whose path 1 is less accurate than the scan (path 0), every other path better than
    the one before it."""

    name = "proxy"

    def __call__(self, candidate, checkpoint=None, report=None) -> Evaluation:
        rmse = [1.0, 1.2] + [0.9 - 0.1 * i for i in range(candidate.num_paths - 2)]
        metrics = pd.DataFrame({"path": range(candidate.num_paths), "rmse": rmse, "abs_rel": rmse})
        return Evaluation(metrics, {"evaluator": "proxy", "seconds": 0.0, "steps": 0, "images_per_second": 0.0})


def _trial(keep_every_exit: bool):
    context = SearchConfig(study="shipping", keep_every_exit=keep_every_exit, **TINY).resolve()
    objective = Objective(context, None)
    objective.evaluator = WorseSecondPath()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    study.optimize(objective, n_trials=1)
    return context, study.trials[0]


@pytest.fixture(scope="module")
def shipped():
    return _trial(keep_every_exit=False)


def test_a_trial_is_scored_as_the_network_that_ships_without_the_exit_worse_than_the_scan(shipped):
    context, trial = shipped
    rec = trial_record(trial)
    trained = Candidate.from_dict(rec.candidate)
    ships = Candidate.from_dict(rec.shipped_candidate)
    assert [d["path"] for d in rec.shipped.dropped] == [1]
    assert ships.num_paths == trained.num_paths - 1 == len(rec.path_metrics)
    assert rec.shipped.trained_paths == [0, *range(2, trained.num_paths)]
    assert [m["rmse"] for m in rec.path_metrics] == [1.0] + [0.9 - 0.1 * i for i in range(trained.num_paths - 2)]
    costs = candidate_cost(ships, (64, 64)).path_latency_ms(context.device)
    assert rec.latency_ms == pytest.approx(costs)
    # the later paths are ready sooner than in the trained network: the dropped head is not computed
    full = candidate_cost(trained, (64, 64)).path_latency_ms(context.device)
    assert all(s < f for s, f in zip(costs[1:], full[2:]))
    expected = anytime_loss(costs, [m["rmse"] for m in rec.path_metrics], context.budgets[0])
    assert trial.values[0] == pytest.approx(expected)
    assert trial_anytime_loss(trial, context.device, context.budgets[0]) == pytest.approx(expected)


def test_keep_every_exit_scores_the_network_as_trained():
    context, trial = _trial(keep_every_exit=True)
    rec = trial_record(trial)
    trained = Candidate.from_dict(rec.candidate)
    assert rec.shipped is None and len(rec.path_metrics) == trained.num_paths
    assert rec.latency_ms == pytest.approx(candidate_cost(trained, (64, 64)).path_latency_ms(context.device))


class TrainedWorseSecondPath(WorseSecondPath):
    """:class:`WorseSecondPath` that also leaves weights (random ones) where the proxy leaves its checkpoint."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def __call__(self, candidate, checkpoint=None, report=None) -> Evaluation:
        if checkpoint is not None:
            torch.manual_seed(0)
            net = build_network(candidate)
            for p in net.parameters():
                p.data.normal_(0, 0.1)
            save_checkpoint(checkpoint, net, TrainConfig(), 0)
        return super().__call__(candidate, checkpoint, report)


def _measured_as(monkeypatch, *shapes):
    """The export's measurements (each call's in turn, the last one thereafter) with their per-path RMSE
    replaced by ``shape(paths)``."""
    real, calls = export_module.measure_export, []

    def measure(model_dir, measurement, input_size):
        metrics, measured = real(model_dir, measurement, input_size)
        shape = shapes[min(len(calls), len(shapes) - 1)]
        calls.append(len(metrics))
        return [dict(m, rmse=r) for m, r in zip(metrics, shape(len(metrics)))], measured
    monkeypatch.setattr(export_module, "measure_export", measure)
    return calls


def _improving(paths: int) -> list[float]:
    return [1.0 - 0.1 * p for p in range(paths)]


@pytest.mark.slow
def test_the_export_ships_the_network_less_its_dropped_exit(tmp_path, monkeypatch, run_cli):
    monkeypatch.setattr(objective_module, "ProxyEvaluator", TrainedWorseSecondPath)
    _measured_as(monkeypatch, _improving)   # the exported graphs confirm the study's figures
    cfg = SearchConfig(study="ships", **{**TINY, "keep_weights": True})
    out = search(cfg.resolve(), SearchRun(n_trials=1, timeout_s=None, reports=tmp_path))
    rec = trial_record(out.study.trials[0])
    assert rec.shipped is not None
    code, _, err = run_cli("export", "--study", "ships", "--reports", tmp_path, "--out", tmp_path / "model",
                           "--eval-frames", 4)
    assert code == 0, err
    manifest = read_manifest(tmp_path / "model")
    assert Candidate.from_dict(manifest.candidate) == Candidate.from_dict(rec.shipped_candidate)
    assert manifest.paths == len(rec.path_metrics) == Candidate.from_dict(rec.candidate).num_paths - 1
    assert [d["path"] for d in manifest.source.dropped_exits] == [1]
    assert manifest.source.trained_candidate == rec.candidate
    code, _, err = run_cli("report", "--study", "ships", "--reports", tmp_path)
    assert code == 0, err
    html = (tmp_path / "ships" / "report.html").read_text()
    assert "Left out of the network that ships" in html and f"{rec.shipped.dropped[0]['exit']} (path 1 as trained) dropped" in html
    dropped = rec.shipped.dropped[0]["exit"]
    assert not [stage.file for stage in manifest.stages if dropped in stage.file]   # its head is not computed
    assert manifest.verification   # the export checked its graphs against the shipped network
    np.save(tmp_path / "scan.npy", np.full(64, 2.0, np.float32))
    Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(tmp_path / "frame.png")
    code, text, err = run_cli("run", tmp_path / "model", "--image", tmp_path / "frame.png", "--scan",
                              tmp_path / "scan.npy", "--deadline", "1000ms", "--json")
    assert code == 0, err
    errors = [m["rmse"] for m in manifest.path_metrics]   # as the export measured them (random weights here)
    assert json.loads(text)["path"] == errors.index(min(errors))   # every path ready: the most accurate


@pytest.mark.slow
def test_the_export_leaves_out_an_exit_its_own_measurement_finds_no_better_and_exports_again(
        tmp_path, monkeypatch, run_cli):
    """The study's figures (estimates, or another size) kept path 2; measured on the exported graphs at the
    deployment size it is less accurate than path 1, so the export ships the network without it."""
    monkeypatch.setattr(objective_module, "ProxyEvaluator", TrainedWorseSecondPath)
    space = yaml.safe_load((SPACES / "tiny.yaml").read_text())
    space["exits"].update(optional=[], required=[0, 1], lidar_only=[True])   # 5 paths, 4 shipped by the study
    (tmp_path / "five.yaml").write_text(yaml.safe_dump(space))
    cfg = SearchConfig(study="reships", **{**TINY, "keep_weights": True, "space": str(tmp_path / "five.yaml")})
    out = search(cfg.resolve(), SearchRun(n_trials=1, timeout_s=None, reports=tmp_path))
    rec = trial_record(out.study.trials[0])
    studied = Candidate.from_dict(rec.shipped_candidate)
    assert studied.num_paths >= 4   # path 2 is not the last
    worse_path_2 = lambda n: [1.0, 0.8, 0.9] + [0.7 - 0.1 * i for i in range(n - 3)]  # noqa: E731
    calls = _measured_as(monkeypatch, worse_path_2, _improving)
    code, out, err = run_cli("export", "--study", "reships", "--reports", tmp_path, "--out", tmp_path / "model",
                           "--eval-frames", 4)
    assert code == 0, err
    assert "dropped: rmse 0.9 is not below 0.8" in out and "measured on the exported graphs at 64x64" in out
    assert calls == [studied.num_paths, studied.num_paths - 1]   # measured, then exported and measured again
    manifest = read_manifest(tmp_path / "model")
    ships = Candidate.from_dict(manifest.candidate)
    assert ships.num_paths == studied.num_paths - 1 == manifest.paths
    by_study, by_export = manifest.source.dropped_exits
    assert by_study == rec.shipped.dropped[0] and "measured_on" not in by_study
    exit_2 = exit_names(studied)[1]
    assert by_export["exit"] == exit_2 and by_export["measured_on"] == "the exported graphs at 64x64"
    assert by_export["path"] == rec.shipped.trained_paths[2] and by_export["better_path"] == rec.shipped.trained_paths[1]
    assert by_export["loss"] == 0.9 and by_export["better_loss"] == 0.8
    assert not [stage.file for stage in manifest.stages if exit_2 in stage.file]   # its head is not computed
    assert [m["rmse"] for m in manifest.path_metrics] == _improving(ships.num_paths)   # measured again
    assert manifest.source.trained_candidate == rec.candidate


@pytest.mark.slow
def test_an_export_of_a_study_that_keeps_every_exit_keeps_them_whatever_it_measures(tmp_path, monkeypatch, run_cli):
    monkeypatch.setattr(objective_module, "ProxyEvaluator", TrainedWorseSecondPath)
    cfg = SearchConfig(study="keeps", keep_every_exit=True, **{**TINY, "keep_weights": True})
    out = search(cfg.resolve(), SearchRun(n_trials=1, timeout_s=None, reports=tmp_path))
    rec = trial_record(out.study.trials[0])
    calls = _measured_as(monkeypatch, lambda n: [1.0, 0.8, 0.9] + [0.7] * (n - 3))
    code, _, err = run_cli("export", "--study", "keeps", "--reports", tmp_path, "--out", tmp_path / "model",
                           "--eval-frames", 4)
    assert code == 0, err
    manifest = read_manifest(tmp_path / "model")
    assert len(calls) == 1 and Candidate.from_dict(manifest.candidate) == Candidate.from_dict(rec.candidate)
    assert manifest.source.dropped_exits is None
