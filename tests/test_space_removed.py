"""What a space and a candidate no longer offer (cascaded exits): what was stored without it still reads,
with the key it had; what asks for it is one line saying why it is gone and what to do."""

import dataclasses

import pytest
import yaml

from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace, paper_candidate

TINY = {"name": "t", "image_encoder": {"blocks": [3], "width_mult": [0.25]},
        "lidar_encoder": {"depth": [2], "width": [8]}, "ecu": {"enabled": [True], "band": [1], "width": [16]},
        "decoder": {"widths": [[16], [8]]}, "exits": {"optional": [0, 1], "head_depth": [1], "residual": [True]}}


def _one_line_saying_why(text: str) -> None:
    assert "\n" not in text and "cascaded exits" in text and "did not pay" in text
    assert "docs/evidence.md" in text and "without them" in text


def test_a_stored_candidate_without_cascaded_exits_reads_with_the_key_it_had():
    residual = dataclasses.replace(paper_candidate(), exit_residual=True)
    assert residual.key == "4e8d73cb84" and paper_candidate().key == "82c6b306e5"
    for stored in (residual.to_dict(), {**residual.to_dict(), "exit_cascade": False}):
        assert Candidate.from_dict(stored) == residual and Candidate.from_dict(stored).key == "4e8d73cb84"
    assert "exit_cascade" not in residual.to_dict()


def test_a_stored_candidate_with_cascaded_exits_is_one_line(tmp_path):
    stored = {**dataclasses.replace(paper_candidate(), exit_residual=True).to_dict(), "exit_cascade": True}
    with pytest.raises(UserError) as err:
        Candidate.from_dict(stored, source="trial 7")
    _one_line_saying_why(str(err.value))
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({"candidate": stored}))
    with pytest.raises(UserError, match="cascaded exits"):
        Candidate.from_yaml(path)


@pytest.mark.parametrize("cascade", [[False, True], [True], True])
def test_a_space_offering_cascaded_exits_is_one_line_exit_2(cascade, tmp_path, run_cli):
    space = {**TINY, "exits": {**TINY["exits"], "cascade": cascade}}
    with pytest.raises(UserError) as err:
        SearchSpace.from_dict(space, source="s.yaml")
    _one_line_saying_why(str(err.value))
    assert "exits.cascade" in str(err.value)
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(space))
    code, out, err_text = run_cli("space", "show", path)
    assert code == 2 and "cascaded exits" in out + err_text


def test_a_space_listing_only_false_reads_as_without_it():
    assert SearchSpace.from_dict({**TINY, "exits": {**TINY["exits"], "cascade": [False]}}).size == \
        SearchSpace.from_dict(TINY).size
