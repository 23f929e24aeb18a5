import dataclasses

import optuna
import pytest
import yaml

from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace, paper_candidate


def test_shipped_spaces_sizes_and_paper_design():
    default = SearchSpace.from_yaml("anytime_depth")
    assert default.size >= 1_000_000      # tests/test_widened_space.py checks size against enumeration
    assert default.contains(paper_candidate())
    paper = SearchSpace.from_yaml("paper")
    assert list(paper.enumerate()) == [paper_candidate()]
    tiny = SearchSpace.from_yaml("tiny")
    cands = list(tiny.enumerate())
    assert 2 <= len(cands) == tiny.size <= 32
    assert len({c.key for c in cands}) == len(cands)


def test_candidate_yaml_round_trip(tmp_path):
    c = paper_candidate()
    p = tmp_path / "c.yaml"
    p.write_text(c.to_yaml())
    assert Candidate.from_yaml(p) == c
    assert Candidate.from_yaml(p).key == c.key
    assert hash(c) == hash(Candidate.from_yaml(p))


def test_candidate_canonical_form_when_ecu_off():
    a = dataclasses.replace(paper_candidate(), ecu=False)
    b = dataclasses.replace(paper_candidate(), ecu=False, lidar_width=8, ecu_band=1)
    assert a == b and a.lidar_depth == 0


def test_sample_stays_in_space_and_params_round_trip():
    space = SearchSpace.from_yaml("anytime_depth")
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(20):
        trial = study.ask()
        cand = space.sample(trial)
        assert space.contains(cand)
        fixed = optuna.trial.FixedTrial(space.params_of(cand))
        assert space.sample(fixed) == cand
        study.tell(trial, 0.0)


def _write(tmp_path, data):
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(bogus=1), "unknown section"),
    (lambda d: d["image_encoder"].update(depth=[1]), "unknown key"),
    (lambda d: d["image_encoder"].update(blocks=[]), "empty"),
    (lambda d: d["image_encoder"].update(blocks=[5]), "stride"),
    (lambda d: d["exits"].update(optional=[7]), "stage"),
    (lambda d: d["image_encoder"].update(width_mult=["wide"]), "positive number"),
    (lambda d: d["ecu"].update(band=[2]), "odd"),
    (lambda d: d["decoder"].update(widths=[]), "per decoder stage"),
])
def test_space_validation_errors(tmp_path, mutate, message):
    data = yaml.safe_load(open(SearchSpace.from_yaml("anytime_depth").source))
    mutate(data)
    with pytest.raises(UserError, match=message):
        SearchSpace.from_yaml(_write(tmp_path, data))


def test_bad_yaml_and_candidate_errors(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("image_encoder: [unclosed")
    with pytest.raises(UserError, match="not valid YAML"):
        SearchSpace.from_yaml(p)
    with pytest.raises(UserError, match="unknown candidate field"):
        Candidate.from_dict({"encoder_blocks": 9, "colour": 1})
    with pytest.raises(UserError, match="last decoder stage"):
        Candidate(exits=(0, 1))
    with pytest.raises(UserError, match="stride"):
        Candidate(encoder_blocks=5)


def test_every_candidate_field_is_one_declared_dimension_that_a_space_file_can_set(tmp_path):
    from explorer.space import DIMENSIONS
    assert sorted(d.field for d in DIMENSIONS) == sorted(f.name for f in dataclasses.fields(Candidate))
    # each declared YAML key reaches its field: a space offering both values of a yes/no dimension has them
    for dim in (d for d in DIMENSIONS if d.kind is bool):
        path = tmp_path / f"{dim.field}.yaml"
        path.write_text(yaml.safe_dump({"name": "s", dim.section: {dim.key: [False, True]}}))
        assert getattr(SearchSpace.from_yaml(path), dim.field) == (False, True), dim.field
