"""The widened space: exits inside the image encoder, a learned LiDAR-only path, stage order."""

import dataclasses
import json

import numpy as np
import pytest
import torch
import yaml

from explorer.cost import candidate_cost, get_device
from explorer.deploy.export import export_network
from explorer.model import build_network, stage_specs
from explorer.deploy.runtime import AnytimeRunner
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
    assert manifest.verification.max_abs_diff <= 1e-4
    assert [s.path for s in manifest.stages] == list(range(WIDE.num_paths))
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


# -- exits that correct the interpolated scan --------------------------------------------------
RESIDUAL = dataclasses.replace(WIDE, exit_residual=True)


def _zero_outputs(net):
    """Every head's last conv (and the LiDAR-only path's) set to output zero."""
    with torch.no_grad():
        for spec in net.specs:
            if spec.path is not None:
                module = net.stages[spec.name]
                last = module.out if hasattr(module, "out") else module.layers[-1]
                last.weight.zero_()
                last.bias.zero_()


def test_residual_exits_correct_path_0_and_plain_ones_replace_it():
    image, scan = torch.rand(2, 3, 32, 48), torch.rand(2, 48) * 4 + 0.5
    for cand, equal in ((RESIDUAL, True), (WIDE, False)):
        net = build_network(cand).eval()
        _zero_outputs(net)
        with torch.no_grad():
            outs = net(image, scan)
        assert len(outs) == cand.num_paths and all(o.shape == (2, 1, 32, 48) for o in outs)
        # a residual head that outputs nothing returns the scan; a plain one returns zeros
        assert all(torch.equal(o, outs[0]) == equal for o in outs[1:])
    names = [s.name for s in stage_specs(RESIDUAL)]
    assert names[0] == "scan_fill" and "scan_fill" not in [s.name for s in stage_specs(WIDE)]
    assert all(s.inputs[-1] == "scan_fill" for s in stage_specs(RESIDUAL) if s.path is not None)


def test_residual_exits_pay_for_the_scan_once_and_keep_prefix_costs():
    tx2 = get_device("tx2")
    plain = candidate_cost(WIDE, (224, 224)).path_latency_ms(tx2)
    cost = candidate_cost(RESIDUAL, (224, 224))
    ms = cost.path_latency_ms(tx2)
    assert all(a < b for a, b in zip(ms, ms[1:])) and all(r > p for r, p in zip(ms[1:], plain[1:]))
    assert all(used[0] == "scan_fill" for used in cost.path_stages)
    # the fill and the adds are a small part of the first path's price
    assert ms[1] - plain[1] < 0.2


def test_residual_exits_export_and_run(tmp_path):
    torch.manual_seed(0)
    net = build_network(RESIDUAL)
    manifest = export_network(net, tmp_path, (32, 48), devices=("tx2",))
    assert manifest.verification.max_abs_diff <= 1e-4
    runner = AnytimeRunner(tmp_path)
    image = np.random.default_rng(0).random((3, 32, 48), dtype=np.float32)
    scan = np.linspace(1, 4, 48, dtype=np.float32)
    scan[5:9] = 0.0     # no returns there: filled from the nearest column, as path 0 does
    full = runner.run(image, scan)
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(image)[None], torch.from_numpy(scan)[None])
    assert full.path == RESIDUAL.num_paths - 1
    assert np.abs(full.depth - ref[-1][0, 0].numpy()).max() <= 1e-4


def test_the_residual_choice_is_a_dimension(tmp_path, run_cli):
    space = SearchSpace.from_yaml(_space(tmp_path, **{"exits.residual": [False, True]}))
    plain = SearchSpace.from_yaml(_space(tmp_path, **{"exits.residual": [False]}))
    assert space.size == 2 * plain.size and space.contains(paper_candidate())
    assert space.contains(dataclasses.replace(paper_candidate(), exit_residual=True))
    assert not plain.contains(dataclasses.replace(paper_candidate(), exit_residual=True))
    assert "exit_residual" in dataclasses.replace(paper_candidate(), exit_residual=True).to_dict()
    code, _, err = run_cli("space", "show", _space(tmp_path, **{"exits.residual": ["sometimes"]}))
    assert code == 2 and "residual" in err and len(err.strip().splitlines()) == 1
