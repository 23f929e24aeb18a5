"""Whatever a user writes where the package parses text (data specs, sizes, search spaces, candidates,
export manifests, probe results), it parses or raises the package's one user-error type: never
anything else. Hypothesis generates the inputs."""

import json

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from explorer.calibration.results_schema import check_results
from explorer.cli._common import _size
from explorer.data import parse_data_spec
from explorer.deploy.manifest import read_manifest
from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-5, 2000), st.floats(allow_nan=True),
                    st.text(max_size=8))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=12)
SPACE_KEYS = st.sampled_from(["name", "image_encoder", "lidar_encoder", "ecu", "decoder", "exits", "precision",
                              "description", "encoder_blocks", "width_mult", "widths", "optional"])


def _parses_or_says_one_line(parse, *args) -> None:
    """``parse(*args)`` returns, or raises the package's user error in one line; nothing else."""
    try:
        parse(*args)
    except UserError as exc:
        assert "\n" not in str(exc)


@SETTINGS
@given(st.text(alphabet="synthetic-seqnyukittiframes:/0123456789.x", max_size=30))
def test_data_specs(spec):
    _parses_or_says_one_line(parse_data_spec, spec)


@SETTINGS
@given(st.text(alphabet="0123456789xX -.e", max_size=12))
def test_sizes(text):
    import argparse
    try:
        h, w = _size(text)
        assert h >= 1 and w >= 1
    except argparse.ArgumentTypeError:   # argparse turns it into one line, exit 2
        pass


@SETTINGS
@given(st.dictionaries(SPACE_KEYS, VALUES, max_size=6))
def test_search_spaces(data):
    _parses_or_says_one_line(SearchSpace.from_dict, data)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["encoder_blocks", "width_mult", "ecu", "decoder_widths", "exits",
                                        "head_depth", "precision", "lidar_depth", "bogus"]), VALUES, max_size=5))
def test_candidates(data):
    _parses_or_says_one_line(Candidate.from_dict, data)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["format", "input_size", "scan_row", "paths", "stages", "candidate"]), VALUES,
                       max_size=6))
def test_export_manifests(tmp_path, data):
    (tmp_path / "manifest.json").write_text(json.dumps(data))
    _parses_or_says_one_line(read_manifest, tmp_path)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["format", "version", "bundle", "device", "conditions", "layers", "stages"]),
                       VALUES, max_size=7))
def test_probe_results(data):
    _parses_or_says_one_line(check_results, data, "results.json")


@SETTINGS
@given(VALUES)
def test_space_yaml_files(tmp_path, data):
    path = tmp_path / "space.yaml"
    path.write_text(yaml.safe_dump(data))
    _parses_or_says_one_line(SearchSpace.from_yaml, path)
