"""The probe's bundle manifest is read confined to its bundle: no graph it names lies outside."""

import json

import pytest

from explorer.probe.formats import BUNDLE_FORMAT, VERSION, ProbeError, load_manifest


def _bundle(tmp_path, files):
    folder = tmp_path / "bundle"
    (folder / "layers").mkdir(parents=True)
    (tmp_path / "secret.onnx").write_bytes(b"outside")
    manifest = {"format": BUNDLE_FORMAT, "version": VERSION,
                "layers": [{"name": f"L{i}", "file": f} for i, f in enumerate(files)],
                "candidates": [{"graphs": [{"file": "layers/a.onnx"}]}]}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


@pytest.mark.parametrize("name", ["../secret.onnx", "layers/../../secret.onnx", "/etc/passwd", "", 7])
def test_a_graph_path_that_leaves_the_bundle_is_one_line(tmp_path, name):
    with pytest.raises(ProbeError, match="lies outside the bundle") as caught:
        load_manifest(_bundle(tmp_path, ["layers/a.onnx", name]))
    assert "\n" not in str(caught.value)


def test_graph_paths_inside_the_bundle_are_read(tmp_path):
    manifest = load_manifest(_bundle(tmp_path, ["layers/a.onnx", "layers/./b.onnx"]))
    assert [layer["file"] for layer in manifest.layers] == ["layers/a.onnx", "layers/./b.onnx"]
