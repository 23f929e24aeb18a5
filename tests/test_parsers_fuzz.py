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


def _one_line(exc: UserError) -> None:
    assert "\n" not in str(exc)


@SETTINGS
@given(st.text(alphabet="synthetic-seqnyukittiframes:/0123456789.x", max_size=30))
def test_data_specs(spec):
    try:
        parse_data_spec(spec)
    except UserError as exc:
        _one_line(exc)


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
    try:
        SearchSpace.from_dict(data)
    except UserError as exc:
        _one_line(exc)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["encoder_blocks", "width_mult", "ecu", "decoder_widths", "exits",
                                        "head_depth", "precision", "lidar_depth", "bogus"]), VALUES, max_size=5))
def test_candidates(data):
    try:
        Candidate.from_dict(data)
    except UserError as exc:
        _one_line(exc)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["format", "input_size", "scan_row", "paths", "stages", "candidate"]), VALUES,
                       max_size=6))
def test_export_manifests(tmp_path, data):
    (tmp_path / "manifest.json").write_text(json.dumps(data))
    try:
        read_manifest(tmp_path)
    except UserError as exc:
        _one_line(exc)


@SETTINGS
@given(st.dictionaries(st.sampled_from(["format", "version", "bundle", "device", "conditions", "layers", "stages"]),
                       VALUES, max_size=7))
def test_probe_results(data):
    try:
        check_results(data, "results.json")
    except UserError as exc:
        _one_line(exc)


@SETTINGS
@given(VALUES)
def test_space_yaml_files(tmp_path, data):
    path = tmp_path / "space.yaml"
    path.write_text(yaml.safe_dump(data))
    try:
        SearchSpace.from_yaml(path)
    except UserError as exc:
        _one_line(exc)
