"""The runner's choice between stage sessions sharing one memory arena and sessions with their own."""

import numpy as np

from explorer.deploy._arena_choice import EXPLORE_EVERY, EXPLORE_EVERY_MAX, EXPLORE_RUNS, ArenaChoice


def _serve(choice: ArenaChoice, stage_ms: list[list[float]], runs: int) -> list[int]:
    """``runs`` runs where set o takes ``stage_ms[o][k]`` ms for stage k; the sets picked."""
    picked = []
    for _ in range(runs):
        o = choice.pick()
        picked.append(o)
        for k, ms in enumerate(stage_ms[o]):
            choice.record(o, k, ms)
    return picked


def test_it_times_both_sets_then_keeps_to_the_faster_one_exploring_the_other():
    choice = ArenaChoice(2, 3)
    picked = _serve(choice, [[1.0, 2.0, 1.0], [1.0, 1.5, 1.0]], 10 * EXPLORE_EVERY)
    assert picked[:4] == [0, 0, 1, 1]   # each set warmed, then timed, before any comparison
    later = picked[EXPLORE_EVERY:]
    assert EXPLORE_RUNS <= later.count(0) < EXPLORE_RUNS * (len(later) // EXPLORE_EVERY)   # explored, less and less
    assert choice.best() == 1


def _explorations(picked: list[int], favoured: int) -> list[int]:
    """The runs (0-based) that start a spell of the set not in favour."""
    return [i for i, o in enumerate(picked) if o != favoured and (i == 0 or picked[i - 1] == favoured)]


def test_while_the_choice_stays_it_looks_at_the_other_set_less_and_less_often():
    choice = ArenaChoice(2, 2)
    _serve(choice, [[1.0, 1.0], [1.3, 1.3]], 2 * EXPLORE_EVERY)
    picked = _serve(choice, [[1.0, 1.0], [1.3, 1.3]], 6 * EXPLORE_EVERY_MAX)
    starts = _explorations(picked, 0)
    gaps = np.diff(starts)
    assert all(b >= a for a, b in zip(gaps, gaps[1:])) and gaps[0] < EXPLORE_EVERY_MAX
    assert gaps[-1] == EXPLORE_EVERY_MAX and max(gaps) == EXPLORE_EVERY_MAX
    assert all(picked[s:s + EXPLORE_RUNS] == [1] * EXPLORE_RUNS for s in starts[:-1])


def test_a_run_after_a_switch_of_set_does_not_count():
    """The first run of a set after the other's finds the caches full of the other's buffers."""
    choice = ArenaChoice(2, 1)
    first = choice.pick()
    choice.record(first, 0, 99.0)   # cold: not kept
    assert choice.ms(first, 0) is None
    again = choice.pick()
    assert again == first
    choice.record(again, 0, 1.0)
    assert choice.ms(first, 0) == 1.0


def test_it_follows_the_machine_when_the_faster_set_changes():
    choice = ArenaChoice(2, 2)
    _serve(choice, [[1.0, 1.0], [1.3, 1.3]], 5 * EXPLORE_EVERY)
    assert choice.best() == 0
    picked = _serve(choice, [[1.4, 1.4], [1.1, 1.1]], EXPLORE_EVERY_MAX + 3 * EXPLORE_EVERY)   # the machine changed
    assert choice.best() == 1
    assert picked[-3 * EXPLORE_EVERY:].count(1) > 2 * EXPLORE_EVERY
    # once it switched, it looks back at the other set within EXPLORE_EVERY runs again
    switched = picked.index(1) + EXPLORE_RUNS
    assert 0 in picked[switched:switched + EXPLORE_EVERY + EXPLORE_RUNS]


def test_stages_timed_in_only_one_set_do_not_decide():
    choice = ArenaChoice(2, 3)
    for o, stage, ms in ((0, 0, 1.0), (1, 0, 2.0), (1, 2, 0.1)):   # stage 2: set 0 never completed it
        choice.samples[o][stage].append(ms)
    assert choice.best() == 0


def test_one_set_is_always_that_set():
    choice = ArenaChoice(1, 2)
    assert set(_serve(choice, [[1.0, 1.0]], 3 * EXPLORE_EVERY)) == {0}


def test_the_runner_keeps_both_sets_and_they_give_the_same_depths(tmp_path):
    import torch
    from explorer.probe import shared_arena
    from explorer.deploy.export import export_network
    from explorer.model import build_network
    from explorer.deploy.runtime import AnytimeRunner
    from explorer.space import SearchSpace
    torch.manual_seed(0)
    cand = SearchSpace.from_yaml("tiny").random_candidates(1, 0)[0]
    export_network(build_network(cand).eval(), tmp_path / "m", (32, 32))
    runner = AnytimeRunner(tmp_path / "m")
    assert len(runner.session_sets) == (2 if shared_arena() else 1)
    rng = np.random.default_rng(0)
    img, scan = rng.random((3, 32, 32), dtype=np.float32), rng.uniform(0.5, 10, 32).astype(np.float32)
    maps = [runner._depths(s, *runner.check(img, scan)) for s in runner.session_sets]
    for other in maps[1:]:
        for a, b in zip(maps[0], other):
            np.testing.assert_array_equal(a, b)
    for _ in range(2 * EXPLORE_EVERY):
        runner.run(img, scan)
    assert sum(runner.arena_choice.runs) == 2 * EXPLORE_EVERY
    if len(runner.session_sets) == 2:
        assert min(runner.arena_choice.runs) >= 2   # each set served, so each was timed
        assert all(runner.arena_choice.ms(1, k) is not None for k in range(1, len(runner.sessions)))


def test_a_runner_can_be_held_to_one_set(tmp_path):
    import pytest
    import torch
    from explorer.probe import shared_arena
    from explorer.deploy.export import export_network
    from explorer.errors import UserError
    from explorer.model import build_network
    from explorer.deploy.runtime import AnytimeRunner
    from explorer.space import SearchSpace
    torch.manual_seed(0)
    export_network(build_network(SearchSpace.from_yaml("tiny").random_candidates(1, 0)[0]).eval(), tmp_path / "m",
                   (32, 32))

    def env_allocator(sess) -> str:
        try:
            return sess.get_session_options().get_session_config_entry("session.use_env_allocators")
        except RuntimeError:   # not set
            return ""
    for arenas in ("shared", "own"):
        runner = AnytimeRunner(tmp_path / "m", arenas=arenas)
        assert len(runner.session_sets) == 1 and runner.sessions is runner.session_sets[0]
        uses = {env_allocator(sess) for _, sess, *_ in runner.sessions}
        if arenas == "own":
            assert "1" not in uses   # arenas of their own
        elif shared_arena():
            assert uses == {"1"}     # the process's one arena
    with pytest.raises(UserError, match="arenas='none'"):
        AnytimeRunner(tmp_path / "m", arenas="none")


def test_the_shared_set_keeps_its_place_unless_another_is_clearly_faster():
    from explorer.deploy._arena_choice import MARGIN
    choice = ArenaChoice(2, 1)
    _serve(choice, [[1.0], [1.0 - MARGIN / 2]], 4 * EXPLORE_EVERY)   # within the margin: noise
    assert choice.best() == 0
    _serve(choice, [[1.0], [1.0 - 2 * MARGIN]], EXPLORE_EVERY_MAX + EXPLORE_EVERY)   # its explorations show it
    assert choice.best() == 1
