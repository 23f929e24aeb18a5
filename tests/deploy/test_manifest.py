"""The runtime reads an export's manifest through one schema and checks every graph against it: an
edited, foreign or half-replaced export is one line, never a crash inside onnxruntime."""

import json
import shutil

import pytest

from explorer.deploy.export import export_network
from explorer.deploy.manifest import MANIFEST, read_manifest
from explorer.deploy.runtime import AnytimeRunner
from explorer.errors import UserError
from explorer.model import build_network
from explorer.space import paper_candidate


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "m"
    export_network(build_network(paper_candidate()), out, (64, 64), devices=())
    return out


def _copy(model, tmp_path, edit=None):
    dst = tmp_path / "m"
    shutil.copytree(model, dst)
    if edit:
        manifest = json.loads((dst / MANIFEST).read_text())
        edit(manifest, dst)
        (dst / MANIFEST).write_text(json.dumps(manifest))
    return dst


def _stage(i):
    def edit(m, dst):
        m["stages"][i]["file"] = "../outside.onnx"
    return edit


CASES = {
    "empty": (lambda m, d: m.clear(), "format"),
    "no stages": (lambda m, d: m.update(stages=[]), "stages"),
    "outside": (_stage(1), "inside the model folder"),
    "bad size": (lambda m, d: m.update(input_size=[0, 64]), "input_size"),
    "scan row": (lambda m, d: m.update(scan_row=64), "scan_row"),
    "text paths": (lambda m, d: m.update(paths="four"), "paths"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_broken_manifest_is_one_line(model, tmp_path, name):
    edit, why = CASES[name]
    folder = _copy(model, tmp_path, edit)
    with pytest.raises(UserError, match=why) as err:
        AnytimeRunner(folder, warmup=False)
    assert "\n" not in str(err.value)


def test_a_changed_graph_does_not_match_the_manifest(model, tmp_path):
    folder = _copy(model, tmp_path)
    manifest = read_manifest(folder)
    a, b = manifest.stages[1].file, manifest.stages[2].file
    (folder / a).write_bytes((folder / b).read_bytes())   # another stage's graph in its place
    with pytest.raises(UserError, match="does not match the manifest"):
        AnytimeRunner(folder, warmup=False)


def test_graphs_without_hashes_are_still_checked_as_a_chain(model, tmp_path):
    def swap(m, dst):
        for s in m["stages"]:
            s.pop("sha256")
        m["stages"][1], m["stages"][2] = m["stages"][2], m["stages"][1]
    folder = _copy(model, tmp_path, swap)
    with pytest.raises(UserError, match="do not match the manifest"):
        AnytimeRunner(folder, warmup=False)


def test_a_whole_export_loads(model):
    assert AnytimeRunner(model, warmup=False).input_size == (64, 64)


def test_an_export_writes_only_what_its_schema_accepts(model, tmp_path):
    """The export goes through the same schema the runtime reads: figures for the wrong number of paths,
    or a measurement without its frames, are refused before anything is written."""
    import pydantic

    from explorer.deploy.manifest import Manifest, Measured, write_manifest
    on_disk = json.loads((model / MANIFEST).read_text())
    write_manifest(tmp_path, read_manifest(model))   # read and written again: the same keys, the same values
    assert json.loads((tmp_path / MANIFEST).read_text()) == on_disk
    for name, value in (("path_metrics", [{"rmse": 0.3}]),
                        ("measured", Measured(data="synthetic", split="val", frames=1, input_size=(64, 64)))):
        manifest = read_manifest(model)
        setattr(manifest, name, value)
        if name == "measured":
            manifest.measured.frames = 0   # set after it was made: a measurement on no frames
        with pytest.raises(pydantic.ValidationError):
            write_manifest(tmp_path / "bad", manifest)
        assert not (tmp_path / "bad" / MANIFEST).exists()
    with pytest.raises(pydantic.ValidationError):
        Manifest.model_validate({**on_disk, "measured": {"data": "synthetic", "split": "val", "input_size": [64, 64]}})


def test_a_manifest_keeps_the_keys_it_does_not_know(model, tmp_path):
    """A newer export's additions (at the top, in a stage, in a record) survive a read and a write, and
    nothing is added at its default."""
    from explorer.deploy.manifest import write_manifest
    folder = _copy(model, tmp_path, lambda m, d: (m.update(added_later={"x": 1}), m["stages"][0].update(hint="y"),
                                                   m["verification"].update(seed=3)))
    manifest = read_manifest(folder)
    assert manifest.added_later == {"x": 1} and manifest.stages[0].hint == "y"
    assert manifest.tuned_size is None and manifest.quantization is None
    on_disk = json.loads((folder / MANIFEST).read_text())
    write_manifest(folder, manifest)
    assert json.loads((folder / MANIFEST).read_text()) == on_disk
    assert "tuned_size" not in on_disk and "quantization" not in on_disk


def test_an_exports_files_are_readable_as_the_umask_allows(tmp_path):
    """An export is copied for other users and services: its files get the mode a plain write would
    give them (0644 under umask 022), not the private mode of the scratch files they are written as."""
    import os
    import stat
    old = os.umask(0o022)
    try:
        export_network(build_network(paper_candidate()), tmp_path / "m", (64, 64), devices=())
    finally:
        os.umask(old)
    files = list((tmp_path / "m").iterdir())
    assert files and {stat.S_IMODE(f.stat().st_mode) for f in files} == {0o644}
    assert stat.S_IMODE((tmp_path / "m").stat().st_mode) == 0o755


def _string_key_reads(source: str) -> list[int]:
    """The lines of ``source`` that read a manifest by string key: ``manifest["paths"]``,
    ``runner.manifest.get("precision")``, ``"quantization" in manifest`` (any name holding "manifest")."""
    import ast

    def manifest(node) -> bool:
        name = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""
        return "manifest" in name.lower()

    def text(node) -> bool:
        return isinstance(node, ast.Constant) and isinstance(node.value, str)

    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Subscript) and manifest(node.value) and text(node.slice):
            found.add(node.lineno)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and manifest(node.func.value)
              and node.func.attr in ("get", "pop", "setdefault") and node.args and text(node.args[0])):
            found.add(node.lineno)
        elif (isinstance(node, ast.Compare) and text(node.left) and any(manifest(c) for c in node.comparators)
              and all(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops)):
            found.add(node.lineno)
    return sorted(found)


def test_the_check_for_string_key_reads_finds_them():
    reads = 'a = manifest["paths"]\nb = self.manifest.get("precision", "fp32")\nc = "quantization" in manifest\n' \
            'bundle_manifest["id"] = 1\nd = manifest_json.pop("x")\n'
    assert _string_key_reads(reads) == [1, 2, 3, 4, 5]
    typed = 'a = manifest.paths\nb = manifest.stages[0].file\nc = metrics["rmse"]\nd = manifest.expected_cost["tx2"]\n'
    assert _string_key_reads(typed) == []


def test_no_code_reads_a_manifest_by_string_key():
    """A manifest is read through its types (``explorer.deploy.manifest.Manifest``, the probe's
    ``BundleManifest``), never by key: a renamed or removed field is then one place to change, and a
    reader of a field that does not exist fails at once."""
    from pathlib import Path

    import explorer
    root = Path(explorer.__file__).parent
    reads = {str(f.relative_to(root.parent)): lines for f in sorted(root.rglob("*.py"))
             if (lines := _string_key_reads(f.read_text()))}
    assert reads == {}, f"string-key reads of a manifest (file: lines): {reads}"
