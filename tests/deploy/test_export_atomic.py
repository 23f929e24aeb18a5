"""An export is written whole: killed at any moment, the folder holds the old export or the new one
(every graph matching the manifest's hashes), and the next export cleans what the dead one left."""

import json
import signal
import subprocess
import sys
import time

import pytest

from explorer.deploy.export import MANIFEST, export_network, file_sha256
from explorer.errors import UserError
from explorer.model import build_network
from explorer.space import paper_candidate

CHILD = """
import sys, torch
from pathlib import Path
from explorer.deploy.export import export_network
from explorer.model import build_network
from explorer.space import paper_candidate
torch.manual_seed(int(sys.argv[2]))
net = build_network(paper_candidate())
print("ready", flush=True)
while True:
    export_network(net, Path(sys.argv[1]), (64, 64), devices=(), source={"seed": int(sys.argv[2])})
"""


def _whole(folder) -> dict:
    manifest = json.loads((folder / MANIFEST).read_text())
    for stage in manifest["stages"]:
        assert file_sha256(folder / stage["file"]) == stage["sha256"], stage["file"]
    assert sorted(p.name for p in folder.iterdir()) == sorted([MANIFEST] + [s["file"] for s in manifest["stages"]])
    return manifest


@pytest.mark.slow
def test_an_export_killed_at_any_moment_leaves_a_whole_export(tmp_path):
    out = tmp_path / "model"
    export_network(build_network(paper_candidate()), out, (64, 64), devices=(), source={"seed": -1})
    seen = set()
    for i, delay in enumerate((0.5, 2.0, 4.0)):
        child = subprocess.Popen([sys.executable, "-c", CHILD, str(out), str(i)], stdout=subprocess.PIPE, text=True)
        assert child.stdout.readline().strip() == "ready"
        time.sleep(delay)
        child.send_signal(signal.SIGKILL)
        child.wait()
        seen.add(_whole(out)["source"]["seed"])
        export_network(build_network(paper_candidate()), out, (64, 64), devices=(), source={"seed": 99})
        assert [p.name for p in tmp_path.iterdir()] == ["model"], "scratch left beside the export"
        assert _whole(out)["source"]["seed"] == 99
    assert seen <= {-1, 99, 0, 1, 2}


def test_an_export_refuses_a_folder_that_is_not_an_export(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my own file")
    with pytest.raises(UserError, match="other files"):
        export_network(build_network(paper_candidate()), mine, (64, 64), devices=())
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match="is a file"):
        export_network(build_network(paper_candidate()), tmp_path / "file", (64, 64), devices=())


def test_a_failed_export_leaves_the_old_one(tmp_path, monkeypatch):
    out = tmp_path / "model"
    first = export_network(build_network(paper_candidate()), out, (64, 64), devices=())
    with pytest.raises(UserError):
        export_network(build_network(paper_candidate()), out, (63, 64), devices=())   # not divisible by the stride
    assert _whole(out)["candidate_key"] == first.candidate_key
    assert [p.name for p in tmp_path.iterdir()] == ["model"]
