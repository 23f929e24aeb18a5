"""--time-limit: the plan sizes what the user left free, in the documented order, and says what it changed."""

import dataclasses
import math

import pytest

from explorer.study import planning
from explorer.study.planning import Speeds, plan_run, replan_finalists

FAST = Speeds(retrain_step_s=0.06, retrain_eval_s=0.5, supernet_step_s=0.2)
SLOW = Speeds(retrain_step_s=0.4, retrain_eval_s=3.0, supernet_step_s=1.1)
FREE = dict(supernet_free=True, finalists_free=True, finalist_steps_free=True)


def plan(speeds, remaining=14 * 60, sampling=180.0, cached=False, **kw):
    args = dict(sampling_s=sampling, supernet_steps=600, supernet_cached=cached, finalists=3, finalist_steps=300,
                baselines=3, **FREE)
    args.update(kw)
    return plan_run(remaining, 15 * 60, speeds, **args)


def test_a_fast_machine_keeps_every_setting_and_finishes_early():
    p = plan(FAST)
    assert (p.supernet_steps, p.sampling_s, p.finalists, p.finalist_steps) == (600, 180.0, 3, 300)
    assert p.expected_s < 10 * 60 and p.changes == () and p.fits


def test_a_middling_machine_trains_a_shorter_supernet_on_the_step_grid():
    p = plan(dataclasses.replace(SLOW, supernet_step_s=0.9, retrain_step_s=0.1), remaining=13 * 60)
    assert planning.MIN_SUPERNET_STEPS < p.supernet_steps < 600 and p.supernet_steps % planning.STEP_GRID == 0
    assert (p.finalists, p.finalist_steps) == (3, 200)     # the finalists' steps gave way first, to 2/3
    assert planning.MIN_SAMPLING_S <= p.sampling_s < 180.0          # sampling gave way first
    assert p.expected_s <= 13 * 60 and any("supernet" in c for c in p.changes)


def test_sampling_gives_way_before_the_supernet():
    speeds = dataclasses.replace(SLOW, supernet_step_s=0.5, retrain_step_s=0.05)
    p = plan(speeds, remaining=10 * 60)
    assert p.supernet_steps == 600 and planning.MIN_SAMPLING_S <= p.sampling_s < 180.0
    assert any("sampling" in c for c in p.changes) and not any("supernet" in c for c in p.changes)


def test_a_slow_machine_shrinks_sampling_then_the_supernet_then_the_finalists():
    p = plan(SLOW)
    assert p.supernet_steps == planning.MIN_SUPERNET_STEPS
    assert planning.MIN_SAMPLING_S <= p.sampling_s < 1.5 * planning.MIN_SAMPLING_S
    assert p.finalists < 3 or p.finalist_steps < 300
    assert p.finalist_steps >= planning.MIN_FINALIST_STEPS
    assert p.expected_s <= 14 * 60 + 1 or any("longer --time-limit" in c for c in p.changes)
    # with more time the same machine keeps more of what was asked
    roomy = plan(SLOW, remaining=40 * 60)
    assert (roomy.finalists, roomy.finalist_steps) == (3, 300) and roomy.sampling_s == 180.0


def test_settings_the_user_gave_are_never_changed():
    p = plan(SLOW, supernet_free=False, finalists_free=False, finalist_steps_free=False)
    assert (p.supernet_steps, p.finalists, p.finalist_steps) == (600, 3, 300)
    assert p.sampling_s == planning.MIN_SAMPLING_S
    assert any("longer --time-limit" in c for c in p.changes) and not p.fits


def test_a_cached_supernet_costs_nothing_and_leaves_its_steps():
    p = plan(SLOW, cached=True, supernet_free=False)
    assert p.supernet_s == 0 and p.supernet_steps == 600
    assert p.finalists + p.finalist_steps > plan(SLOW).finalists + plan(SLOW).finalist_steps


def test_no_sampling_cap_gives_sampling_what_is_left():
    p = plan(FAST, sampling=None, supernet_free=False)
    assert math.isclose(p.expected_s, 14 * 60, rel_tol=1e-6)


def test_a_trial_that_may_run_past_the_deadline_is_reserved():
    a, b = plan(FAST, sampling=None, supernet_free=False), plan(FAST, sampling=None, supernet_free=False, trial_s=30)
    assert math.isclose(a.sampling_s - b.sampling_s, 30)


def test_finalists_are_replanned_to_the_time_really_left():
    p = plan(FAST)
    assert replan_finalists(p, 14 * 60, FAST, 3, True, True) == p      # plenty: unchanged
    late = replan_finalists(p, 60, FAST, 3, True, True)
    assert late.finalists == 1 and late.finalist_steps < 300 and late.retrain_s < p.retrain_s
    assert "re-planned" in late.changes[-1]
    fixed = replan_finalists(p, 60, FAST, 3, False, False)
    assert (fixed.finalists, fixed.finalist_steps) == (3, 300)


def test_the_plan_says_what_it_will_do():
    text = plan(FAST).describe()
    assert "supernet" in text and "sampling 3.0 min" in text and "3 finalist(s) and 3 baseline(s)" in text
    assert dataclasses.asdict(plan(FAST))["limit_s"] == 900


def test_a_step_is_timed_after_the_warm_up():
    # step 1 ends at 0 s, step 2 took 2 s (a fresh process), then 0.5 s each with one outlier
    marks = {1: 0.0, 2: 2.0, 3: 2.5, 4: 3.0, 5: 4.5, 6: 5.0}
    assert planning._seconds_per_step(marks) == 0.5
    assert planning._seconds_per_step({1: 0.0, 2: 1.0}) == 1.0


def test_sampling_is_replanned_to_what_the_supernet_left():
    p = plan(SLOW, remaining=14 * 60)
    assert planning.replan_sampling(p, 14 * 60 - p.supernet_s, 180.0) == p        # on time: unchanged
    early = planning.replan_sampling(p, 14 * 60 - p.supernet_s / 2, 180.0)         # the supernet ran 2x faster
    assert early.sampling_s > p.sampling_s and early.sampling_s <= 180.0 and "re-planned" in early.changes[-1]
    late = planning.replan_sampling(p, 60, 180.0)
    assert late.sampling_s < planning.MIN_SAMPLING_S + 5   # down to the minimum (a change under 5 s is no change)


def test_baselines_are_planned_by_their_measured_training_step():
    from explorer.study.search import SearchConfig, baseline_load
    cfg = SearchConfig(study="x", baselines=("paper", "s2d-resnet18", "fastdepth"))
    measured = Speeds(0.1, 1.0, 0.2, baseline_step_s=(("s2d-resnet18", 0.15), ("fastdepth", 0.07)))
    assert baseline_load(cfg, measured) == pytest.approx(1.0 + 1.5 + 0.7)
    by_macs = baseline_load(cfg)       # no measurement: a reference network's MACs over the paper design's
    assert by_macs > 3.0 and baseline_load(SearchConfig(study="x")) == 3.0


def test_finalists_are_planned_by_their_measured_training_step_once_known():
    unknown = FAST
    known = dataclasses.replace(FAST, finalist_step_s=(0.06, 0.03, 0.09))
    assert unknown.finalist_load(3) == pytest.approx(3 * planning.FINALIST_SIZE)
    assert known.finalist_load(2) == pytest.approx(1.5) and known.finalist_load(3) == pytest.approx(3.0)
    assert known.finalist_load(4) == pytest.approx(4 * planning.FINALIST_SIZE)   # more than were measured
    fixed = planning.retrain_seconds(known, 0, 0, 300)
    assert planning.retrain_seconds(known, 2, 0, 300) == pytest.approx(
        planning.SAFETY * 1.5 * (300 * 0.06 + 0.5))
    assert fixed == 0
    # measured smaller than assumed, the same time left keeps more of the recipe
    p = plan(FAST)
    tight = p.retrain_s * 0.7 + planning.RESERVE_S
    k, u = replan_finalists(p, tight, known, 3, True, True), replan_finalists(p, tight, unknown, 3, True, True)
    assert (k.finalists, k.finalist_steps) > (u.finalists, u.finalist_steps)


def test_the_machine_is_measured_for_each_baseline_and_finalist():
    import torch
    from conftest import TINY_DATA
    from explorer.data import open_dataset
    from explorer.study.search import SearchConfig
    cfg = SearchConfig(study="x", space="tiny", data=TINY_DATA, train_size=(32, 32), batch_size=4, val_limit=4)
    tr = open_dataset(TINY_DATA, "train", (32, 32))
    va = open_dataset(TINY_DATA, "val", (32, 32), train_augment=False)
    from explorer.space import SearchSpace
    finalists = tuple(SearchSpace.from_yaml("tiny").random_candidates(2, seed=0))
    speeds = planning.measure_speeds(cfg, tr, va, torch.device("cpu"), supernet=False, steps=4,
                                     baselines=("fastdepth-pruned", "paper-nee"), finalists=finalists)
    assert [name for name, _ in speeds.baseline_step_s] == ["fastdepth-pruned", "paper-nee"]
    assert all(step > 0 for _, step in speeds.baseline_step_s) and speeds.relative_training("paper-nee") > 0
    assert len(speeds.finalist_step_s) == 2 and all(step > 0 for step in speeds.finalist_step_s)
    assert speeds.relative_training("s2d-resnet18") is None and speeds.supernet_step_s == 0


def test_finalists_shrunk_on_a_busy_machine_come_back_when_it_is_free():
    busy = plan(SLOW, remaining=8 * 60)                 # measured while the machine was loaded
    assert (busy.finalists, busy.finalist_steps) < (3, 300)
    # measured again at the end of sampling: fast now, with time left for what was asked
    back = replan_finalists(busy, 6 * 60, FAST, 3, True, True, wanted=(3, 300))
    assert (back.finalists, back.finalist_steps) == (3, 300) and "0.06 s a step" in back.changes[-1]
    # still slow: no more than fits, and never more than was asked
    still = replan_finalists(busy, 6 * 60, SLOW, 3, True, True, wanted=(3, 300))
    assert still.finalists == 1 and still.retrain_s <= 1.05 * (6 * 60 - planning.RESERVE_S)   # steps sized linearly
    assert still.finalists <= 3 and still.finalist_steps <= 300
    # settings the user gave never move
    fixed = replan_finalists(busy, 6 * 60, FAST, 3, False, False, wanted=(3, 300))
    assert (fixed.finalists, fixed.finalist_steps) == (busy.finalists, busy.finalist_steps)


def test_a_short_replan_shortens_the_finalists_before_dropping_one():
    p = plan(FAST)
    need = p.retrain_s
    # 20% short: 3 finalists at fewer steps (not below two thirds), rather than 2 at 300
    short = replan_finalists(p, need * 0.8 + planning.RESERVE_S, FAST, 3, True, True)
    assert short.finalists == 3 and 200 <= short.finalist_steps < 300
    assert short.retrain_s <= need * 0.8 + 1
    # far shorter: one finalist goes, and the steps stay at two thirds or more while that fits
    shorter = replan_finalists(p, need * 0.55 + planning.RESERVE_S, FAST, 3, True, True)
    assert shorter.finalists < 3 and shorter.finalist_steps >= 200


def test_the_finalists_steps_give_way_to_two_thirds_before_the_supernet_shrinks():
    # a machine of this project's (0.64 s a supernet step, 0.21 s a retraining step) with 12.5 min left
    # after the data: the full recipe leaves the supernet its minimum, two thirds of it 400 steps
    speeds = Speeds(retrain_step_s=0.21, retrain_eval_s=8.0, supernet_step_s=0.64)
    p = plan(speeds, remaining=12.5 * 60)
    assert p.finalists == 3 and p.finalist_steps == 200
    assert p.supernet_steps == 400
    assert p.expected_s <= 12.5 * 60 + 1
    assert p.changes[0] == "finalists retrained 200 steps instead of 300"
    kept = plan(speeds, remaining=12.5 * 60, finalist_steps_free=False)   # steps the user gave stay...
    assert kept.finalist_steps == 300 and kept.supernet_steps == planning.MIN_SUPERNET_STEPS   # ...the supernet pays
    # a cached supernet leaves the finalists their recipe
    assert plan(speeds, remaining=12.5 * 60, cached=True, supernet_free=False).finalist_steps == 300


def test_a_supernet_that_runs_long_stops_where_the_rest_needs_its_minimum():
    limit = planning.TimeLimit(15 * 60, started=1000.0)
    p = plan(SLOW, remaining=14 * 60)
    latest = planning.supernet_deadline(p, limit, SLOW, paper_baseline=True, sampling_s=180.0)
    rest = planning.RESERVE_S + p.trial_s + planning.MIN_SAMPLING_S + planning.retrain_seconds(
        SLOW, 1, 1.0, planning.MIN_FINALIST_STEPS)
    assert latest == pytest.approx(1000.0 + 15 * 60 - rest)
    # the planned supernet ends well before it: only a machine that slowed a lot reaches it
    assert 1000.0 + 60 + p.supernet_s < latest
    # without finalists, and with a shorter sampling cap, less is kept back
    bare = dataclasses.replace(p, finalists=0)
    assert planning.supernet_deadline(bare, limit, SLOW, True, 30.0) == pytest.approx(
        1000.0 + 15 * 60 - planning.RESERVE_S - p.trial_s - 30.0)


def test_finalists_the_time_limit_stopped_are_blamed_on_what_stopped_them():
    p = plan(SLOW, supernet_free=False, finalists_free=False, finalist_steps_free=False)
    fixed = planning.not_retrained(2, p, left_s=p.retrain_s / 3)     # the plan itself did not fit
    assert "needed about" in fixed and "longer --time-limit" in fixed and "slower" not in fixed
    slowed = planning.not_retrained(1, p, left_s=p.retrain_s + 60)   # it fitted, the machine slowed
    assert "ran slower than planned" in slowed and slowed.startswith("1 finalist(s)")


@pytest.mark.parametrize("fixed, blamed", [(True, "the plan did not fit"), (False, "ran slower than planned")])
def test_a_stopped_supernet_is_blamed_on_what_stopped_it(monkeypatch, fixed, blamed):
    import explorer.study.search as search_module
    monkeypatch.setattr(search_module, "read_supernet", lambda path: {"step": 94, "recipe": {"steps": 300}})
    p = plan(SLOW, supernet_free=not fixed, finalists_free=not fixed, finalist_steps_free=not fixed)
    note = search_module._note_unfinished("supernet.pt", p).changes[-1]
    assert note.startswith("supernet stopped at step 94 of 300") and blamed in note
