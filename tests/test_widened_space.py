"""The widened space: exits inside the image encoder, a learned LiDAR-only path, stage order."""

import dataclasses
import json

import numpy as np
import pytest
import torch
import yaml

from explorer.cost import candidate_cost, get_device
from explorer.deploy import export_network
from explorer.model import build_network, stage_specs
from explorer.runtime import AnytimeRunner
from explorer.space import Candidate, SearchSpace, paper_candidate

WIDE = Candidate(encoder_blocks=6, width_mult=0.25, lidar_depth=4, lidar_width=8, ecu_band=1, ecu_width=16,
                 decoder_widths=(32, 16, 8, 8), exits=(0, 2, 4), encoder_exits=(3, 5), lidar_exit=True,
                 lidar_first=True)


@pytest.mark.parametrize("size", [(32, 48), (64, 64), (48, 96)])
@pytest.mark.parametrize("first", [False, True])
def test_every_path_gives_a_full_size_depth_map(size, first):
    cand = dataclasses.replace(WIDE, lidar_first=first)
    net = build_network(cand).eval()
    image, scan = torch.rand(2, 3, *size), torch.rand(2, size[1]) * 4 + 0.5
    with torch.no_grad():
        outs = net(image, scan)
    assert len(outs) == cand.num_paths == 1 + 1 + 2 + 3
    assert all(o.shape == (2, 1, *size) for o in outs)


def test_stage_order_and_fusion():
    names = [s.name for s in stage_specs(WIDE)]
    assert names[:3] == ["lidar_exit", "lidar_encoder", "image_encoder"]
    assert names.index("exit_b3") < names.index("image_encoder_4") < names.index("exit_b5")
    late = dataclasses.replace(WIDE, lidar_first=False)
    names = [s.name for s in stage_specs(late)]
    assert names.index("lidar_encoder") > names.index("image_encoder_6")       # after the whole encoder
    fused = {s.name: s.inputs for s in stage_specs(WIDE)}
    assert fused["exit_b3"] == ("skip_s4", "lidar_s4") and fused["exit_b5"] == ("skip_s8", "lidar_s8")
    # the order only exists where it matters: without encoder exits it is canonical
    assert dataclasses.replace(WIDE, encoder_exits=()).lidar_first is False


def test_costs_are_prefixes_of_the_execution():
    tx2 = get_device("tx2")
    cost = candidate_cost(WIDE, (224, 224))
    ms = cost.path_latency_ms(tx2)
    assert all(a < b for a, b in zip(ms, ms[1:]))
    stages = [s.name for s in stage_specs(WIDE)]
    for i, used in enumerate(cost.path_stages, start=1):
        head = next(s.name for s in stage_specs(WIDE) if s.path == i)
        assert list(used) == stages[:stages.index(head) + 1]     # everything before it, earlier heads too
    # the LiDAR-only path comes first; its own stage costs well under a millisecond on tx2 (the
    # profile's fixed per-inference overhead comes on top, as for every first output)
    paper_first = candidate_cost(paper_candidate()).path_latency_ms(tx2)[1]
    assert ms[1] - tx2.inference_overhead_ms < 0.5 and ms[1] < 0.5 * paper_first
    # an encoder exit comes before the whole encoder has run
    assert ms[2] < candidate_cost(dataclasses.replace(WIDE, encoder_exits=(), lidar_exit=False)).path_latency_ms(tx2)[1]


def test_export_and_runtime_return_every_path(tmp_path):
    torch.manual_seed(0)
    net = build_network(WIDE)
    manifest = export_network(net, tmp_path, (32, 48), devices=("tx2",))
    assert manifest["verification"]["max_abs_diff"] <= 1e-4
    assert [s["path"] for s in manifest["stages"]] == list(range(WIDE.num_paths))
    runner = AnytimeRunner(tmp_path)
    image = np.random.default_rng(0).random((3, 32, 48), dtype=np.float32)
    scan = np.linspace(1, 4, 48, dtype=np.float32)
    full = runner.run(image, scan)
    assert full.path == WIDE.num_paths - 1 and [p for p, _ in full.completed] == list(range(WIDE.num_paths))
    assert runner.run(image, scan, deadline_ms=0).path == 0
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(image)[None], torch.from_numpy(scan)[None])

    def halt_after_lidar(path, ready):
        if path == 1:
            runner.halt()
    early = runner.run(image, scan, on_path=halt_after_lidar)
    assert early.halted and early.path == 1
    assert np.abs(early.depth - ref[1][0, 0].numpy()).max() <= 1e-4


def _space(tmp_path, **changes):
    base = yaml.safe_load(open(SearchSpace.from_yaml("anytime_depth").source))
    for key, value in changes.items():
        section, field = key.split(".")
        base[section][field] = value
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump(base))
    return f


@pytest.mark.parametrize("exits,msg", [([4, 12], "no exit place"), ([1], "no exit place"), ([7], "no exit place")])
def test_an_exit_where_no_stage_exists_is_one_line_exit_2(tmp_path, run_cli, exits, msg):
    code, _, err = run_cli("space", "show", _space(tmp_path, **{"image_encoder.exits": exits}))
    assert code == 2 and msg in err and len(err.strip().splitlines()) == 1


def test_size_counts_every_distinct_candidate():
    space = SearchSpace.from_dict({
        "image_encoder": {"blocks": [6, 7], "width_mult": [0.25], "exits": [3, 5]},
        "lidar_encoder": {"depth": [4], "width": [8, 16], "first": [False, True]},
        "ecu": {"enabled": [False, True], "band": [1], "width": [16]},
        "decoder": {"widths": [[32], [16], [8], [8]]},
        "exits": {"optional": [0], "head_depth": [1, 2], "head_width": [8], "lidar_only": [False, True]}})
    cands = list(space.enumerate())
    assert len(cands) == len(set(cands)) == space.size
    assert all(space.contains(c) for c in cands)
    # Optuna's view of a candidate gives the candidate back
    import optuna
    for c in cands[::17]:
        assert space.sample(optuna.trial.FixedTrial(space.params_of(c))) == c


def test_old_candidates_keep_their_keys():
    # new fields at their defaults are left out of the dict, so names of stored trials do not change
    assert "encoder_exits" not in paper_candidate().to_dict()
    assert paper_candidate().key == "82c6b306e5"
    assert json.loads(json.dumps(WIDE.to_dict()))["encoder_exits"] == [3, 5]
    assert SearchSpace.from_yaml("anytime_depth").contains(paper_candidate())
