"""Whole-space enumeration: the array arithmetic gives exactly the per-candidate rows (``candidate_rows``),
in the space's order, streamed to CSV (and Parquet) whole or not at all, with the Pareto front of
the costs over every candidate."""

from __future__ import annotations

import itertools
import random

import numpy as np
import pandas as pd
import pytest

from explorer.cost import enumerate as enum
from explorer.cost.enumerate import (candidate_rows, enumerate_space, front_columns, pareto_front, space_grid,
                                     write_enumeration)
from explorer.errors import UserError
from explorer.space import SearchSpace

#: every kind of choice the default space has, few of each: encoder exits, stage order, the LiDAR-only
#: exit, residual exits, two head depths, a required exit, two precisions, two working sizes
MIXED = {
    "name": "mixed",
    "image_encoder": {"blocks": [6, 7], "width_mult": [0.5], "exits": [3, 5]},
    "lidar_encoder": {"depth": [4], "width": [8], "first": [False, True]},
    "ecu": {"enabled": [False, True], "band": [1], "width": [64]},
    "decoder": {"widths": [[64], [32], [16], [8, 16]]},
    "exits": {"optional": [0, 2], "required": [1], "head_depth": [1, 2], "head_width": [8],
              "lidar_only": [False, True], "residual": [False, True]},
    "precision": ["fp32", "int8"],
    "downscale": [1, 2],
}
SIZE = (64, 96)


@pytest.fixture(scope="module")
def mixed() -> SearchSpace:
    return SearchSpace.from_dict(MIXED, source="mixed")


def reference(space, device, budget, candidates=None, input_size=SIZE) -> pd.DataFrame:
    return pd.DataFrame(list(candidate_rows(space, device, budget, input_size, candidates)))


@pytest.mark.parametrize("name", ["tiny", "paper", "mixed"])
def test_grid_rows_are_the_spaces_candidates_in_order(name, mixed):
    space = mixed if name == "mixed" else SearchSpace.from_yaml(name)
    grid = space_grid(space, "tx2", "time:uniform:33ms", SIZE)
    assert grid.size == space.size
    assert [grid.candidate(i) for i in range(grid.size)] == list(space.enumerate())


@pytest.mark.parametrize("budget", ["time:uniform:33ms", "time:uniform:4ms", "time:exponential:8ms",
                                    "time:truncnormal:10ms:3ms", "energy:uniform:0.2J", "trace"])
def test_array_rows_equal_the_per_candidate_rows(budget, mixed, tmp_path):
    if budget == "trace":
        (tmp_path / "deadlines.csv").write_text("deadline_ms\n" + "\n".join(map(str, range(1, 40, 3))) + "\n")
        budget = f"time:trace:{tmp_path / 'deadlines.csv'}"
    got = enumerate_space(mixed, "tx2", budget, SIZE)
    want = reference(mixed, "tx2", budget)
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert set(got["paths"]) == set(range(3, 9))   # every count of paths the space has, up to 8
    grid = space_grid(mixed, "tx2", budget, SIZE)
    rows = np.arange(0, mixed.size, 7)
    assert grid.csv(grid.costs(rows)) == want.iloc[rows].to_csv(index=False, header=False)


def test_a_random_sample_of_the_default_space_equals_the_per_candidate_rows():
    space = SearchSpace.from_yaml("anytime_depth")
    grid = space_grid(space, "tx2", "time:uniform:33ms")
    rows = np.array(sorted(random.Random(0).sample(range(space.size), 300)) + [space.size - 1])
    candidates = [grid.candidate(int(r)) for r in rows]
    assert [grid.candidate(i) for i in range(500)] == list(itertools.islice(space.enumerate(), 500))
    want = reference(space, "tx2", "time:uniform:33ms", candidates, (224, 224))
    costs = grid.costs(rows)
    pd.testing.assert_frame_equal(grid.frame(costs), want, check_exact=True)
    assert grid.csv(costs) == want.to_csv(index=False, header=False)


def brute_front(values: np.ndarray) -> list[int]:
    return [i for i, v in enumerate(values)
            if not any((w <= v).all() and (w < v).any() for w in values)]


@pytest.mark.parametrize("columns", [1, 2, 3, 4])
def test_pareto_front_is_every_undominated_row(columns):
    rng = np.random.default_rng(columns)
    for n in (1, 5, 300):
        values = rng.integers(0, 6, size=(n, columns)).astype(float)   # ties and equal rows
        assert pareto_front(values).tolist() == brute_front(values)
    spread = rng.random((1500, columns))
    assert pareto_front(spread).tolist() == brute_front(spread)


def test_streamed_csv_and_front_over_several_chunks(mixed, tmp_path, monkeypatch):
    monkeypatch.setattr(enum, "CHUNK_ROWS", 333)
    seen = []
    done = write_enumeration(mixed, "rpi4", "time:uniform:20ms", SIZE, csv=tmp_path / "all.csv",
                             front=("p_path0", "params", "p_last"), progress=lambda i, n: seen.append((i, n)))
    want = reference(mixed, "rpi4", "time:uniform:20ms")
    assert (tmp_path / "all.csv").read_text() == want.to_csv(index=False)
    assert seen[-1] == (mixed.size, mixed.size) and len(seen) == -(-mixed.size // 333)
    objectives = np.stack([want["p_path0"], want["params"], -want["p_last"]], axis=1)
    front = want.iloc[brute_front(objectives)]
    assert done.size == mixed.size and done.front_columns == ("p_path0", "params", "p_last")
    assert sorted(done.front["key"]) == sorted(front["key"])
    assert done.front["p_path0"].is_monotonic_increasing
    assert not list(tmp_path.glob(".all.csv.*"))


def test_an_enumeration_that_fails_leaves_no_file(mixed, tmp_path):
    def stop(i, n):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        write_enumeration(mixed, "tx2", "time:uniform:33ms", SIZE, csv=tmp_path / "all.csv", progress=stop)
    assert list(tmp_path.iterdir()) == []


def test_parquet_holds_the_same_table(mixed, tmp_path):
    pytest.importorskip("pyarrow")
    write_enumeration(mixed, "tx2", "time:uniform:33ms", SIZE, parquet=tmp_path / "all.parquet")
    got = pd.read_parquet(tmp_path / "all.parquet")
    want = reference(mixed, "tx2", "time:uniform:33ms")
    pd.testing.assert_frame_equal(got, want, check_exact=True, check_dtype=False)


def test_parquet_without_pyarrow_is_one_line(mixed, tmp_path, monkeypatch):
    import builtins
    real_import = builtins.__import__

    def no_pyarrow(name, *args, **kwargs):
        if name.startswith("pyarrow"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)
    monkeypatch.setattr(builtins, "__import__", no_pyarrow)
    with pytest.raises(UserError, match="pyarrow"):
        write_enumeration(mixed, "tx2", "time:uniform:33ms", SIZE, parquet=tmp_path / "all.parquet")
    assert list(tmp_path.iterdir()) == []


def test_front_columns_are_checked():
    assert front_columns("p_path0, params") == ("p_path0", "params")
    for bad in ("", "p_path0,p_path0", "key", "paths"):
        with pytest.raises(UserError, match="--front"):
            front_columns(bad)


def test_enumerate_command_prints_the_front(run_cli, tmp_path):
    code, out, err = run_cli("enumerate", "--space", "tiny", "--device", "rpi4", "--input-size", "64x64",
                             "--csv", tmp_path / "t.csv", "--front", "p_path0,params", "--top", "1")
    assert code == 0, err
    said = " ".join(out.split())   # the table's title wraps in a narrow terminal
    assert "Pareto front of p_path0, params" in said and "the first 1 shown" in said
    frame = pd.read_csv(tmp_path / "t.csv")
    assert len(frame) == 16 and list(frame.columns) == list(enum.COLUMNS)
    code, out, err = run_cli("enumerate", "--space", "tiny", "--front", "p_path0,speed")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--front" in err


def test_the_commands_default_front_is_the_librarys():
    from explorer.cli import build_parser
    args = build_parser().parse_args(["enumerate"])
    assert front_columns(args.front) == enum.DEFAULT_FRONT
    action = next(a for a in build_parser()._subparsers._group_actions[0].choices["enumerate"]._actions
                  if "--front" in a.option_strings)
    assert all(name in action.help for name in enum.FRONT_COLUMNS)   # the help lists every column
