"""bench_table2 (experiments/table2.py): each of the paper's Table 2 columns gets the study's best
estimate re-scored for it, and every network is scored as it ships."""

from __future__ import annotations

import json

import optuna
import pytest
from optuna.distributions import FloatDistribution
from optuna.trial import TrialState, create_trial

from experiments import table2
from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.model.shipped import ship
from explorer.space import Candidate, paper_candidate
from explorer.study.records import record_values
from explorer.study.results import compact_workloads

#: a slow network with an accurate last path and a fast one, less accurate
SLOW = paper_candidate()
FAST = Candidate(encoder_blocks=6, width_mult=0.25, lidar_depth=4, lidar_width=8, ecu_band=1, ecu_width=16,
                 decoder_widths=(64, 32, 16, 16), exits=(0, 4))


def test_columns_are_named_by_device_and_budget():
    assert table2.column("tx2", "time:uniform:33ms") == "tx2_t33ms"
    assert table2.column("rpi4", "energy:uniform:0.25J") == "rpi4_e0_25j"
    assert len({table2.column(d, b) for d in table2.DEVICES for b in table2.BUDGETS}) == 10


def _estimate(candidate: Candidate, errors: list[float]):
    cost = candidate_cost(candidate)
    tx2 = get_device("tx2")
    pm = cost.path_params_macs()
    attrs = record_values(candidate=candidate.to_dict(), candidate_key=candidate.key,
                          params=[p for p, _ in pm], macs=[m for _, m in pm],
                          latency_ms=cost.path_latency_ms(tx2), energy_j=cost.path_energy_j(tx2),
                          workloads=compact_workloads(cost), path_metrics=[{"rmse": e} for e in errors],
                          evaluator={"evaluator": "supernet"})
    return create_trial(state=TrialState.COMPLETE, value=1.0, params={"x": 0.0},
                        distributions={"x": FloatDistribution(0, 1)}, user_attrs=attrs)


def test_each_column_picks_the_best_estimate_rescored_for_it():
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study()
    study.add_trials([_estimate(SLOW, [1.0, 0.5, 0.45, 0.4, 0.2]), _estimate(FAST, [1.0, 0.6, 0.5])])
    picks = table2.column_picks(study)
    for device in table2.DEVICES:
        for budget in table2.BUDGETS:
            expected = min((SLOW, FAST), key=lambda c: anytime_loss(
                candidate_cost(c).path_costs(get_device(device), budget.split(":")[0]),
                [1.0, 0.5, 0.45, 0.4, 0.2] if c == SLOW else [1.0, 0.6, 0.5], budget))
            assert picks[table2.column(device, budget)] == expected
    assert set(picks.values()) == {SLOW, FAST}   # the fast network wins where the slow one is late


def test_each_column_prices_the_network_that_ships():
    errors = [1.0, 1.1, 0.5, 0.4, 0.3]    # path 1 no better than the scan: left out
    shipped = ship(SLOW, errors)
    losses = table2.shipped_losses(shipped.candidate, shipped.losses(errors), (224, 224))
    cost = candidate_cost(shipped.candidate)
    assert losses["tx2_t33ms"] == pytest.approx(anytime_loss(cost.path_costs(get_device("tx2"), "time"),
                                                             [1.0, 0.5, 0.4, 0.3], "time:uniform:33ms"))
    as_trained = table2.shipped_losses(SLOW, errors, (224, 224))
    assert as_trained["tx2_t33ms"] > losses["tx2_t33ms"]   # the dropped head delayed every later path


@pytest.mark.slow
def test_the_experiment_writes_every_column_for_every_seed(tmp_path, monkeypatch):
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    from explorer.study.config import SearchConfig
    from explorer.study.storage import local_url, open_storage
    from conftest import TINY_DATA
    from experiments.lib.retraining import Retrained
    cfg = SearchConfig(study="t2", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32), val_limit=4)
    study = optuna.create_study(study_name="t2", storage=open_storage(local_url("t2", tmp_path), "t2", reports=tmp_path))
    study.set_user_attr("config", cfg.to_dict())
    study.add_trials([_estimate(SLOW, [1.0, 0.5, 0.45, 0.4, 0.2]), _estimate(FAST, [1.0, 0.6, 0.5])])
    trained = []

    def fake_retrained(network, recipe, seed, data, context):
        trained.append((network.candidate.key, seed))
        return Retrained(network.candidate, [],
                         [1.0] + [0.5 - 0.05 * i for i in range(network.candidate.num_paths - 1)])
    monkeypatch.setattr(table2, "retrained", fake_retrained)
    table2.bench_table2(["--study", "t2", "--reports", str(tmp_path), "--reps", "3", "--results",
                         str(tmp_path / "results")])
    assert sorted(trained) == sorted((key, seed) for key in {SLOW.key, FAST.key} for seed in (100, 101, 102))
    record = json.loads(next((tmp_path / "results" / "bench_table2").glob("*.json")).read_text())
    figures = {f["name"]: f for f in record["figures"]}
    assert len([name for name in figures if name.startswith("ratio_")]) == 10
    assert all(len(f["reps"]) == 3 for f in figures.values())
    for name, f in figures.items():
        if name.startswith("ratio_"):
            col = name[len("ratio_"):]
            assert f["median"] == pytest.approx(figures[f"explorer_{col}"]["median"] / figures[f"paper_{col}"]["median"])
