"""Every user mistake is one line on stderr and exit status 2, with no traceback, and creates or
changes nothing: each command is run with bad inputs in a subprocess, in a folder and a cache whose
every file is checksummed before and after."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

GOOD_POSE = " ".join(str(x) for x in np.eye(4)[:3].reshape(-1))


def _frames(folder: Path, intrinsics: str = "40 40 16 16", poses: str | None = None) -> None:
    folder.mkdir()
    for i in range(4):
        Image.fromarray(np.full((32, 32, 3), 40 * i, np.uint8)).save(folder / f"{i:04d}.png")
    (folder / "intrinsics.txt").write_text(intrinsics)
    if poses is not None:
        (folder / "poses.txt").write_text(poses)


def _bomb_png(path: Path) -> None:
    Image.new("RGB", (32, 32)).save(path)
    raw = bytearray(path.read_bytes())
    raw[16:24] = (40000).to_bytes(4, "big") * 2
    raw[29:33] = zlib.crc32(bytes(raw[12:29])).to_bytes(4, "big")
    path.write_bytes(bytes(raw))


def _damaged_study(journal: Path) -> None:
    """A study whose one trial's stored metrics are not a list of per-path figures."""
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="dmg", storage=JournalStorage(JournalFileBackend(str(journal))))
    study.add_trial(optuna.trial.create_trial(values=[1.0], user_attrs={"path_metrics": "oops", "workloads": {}}))


def _workspace(root: Path) -> None:
    """The files the bad invocations point at."""
    (root / "random.bin").write_bytes(np.random.default_rng(0).bytes(3000))
    lines = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)]
    (root / "bomb.yaml").write_text("\n".join(lines) + "\n")
    _frames(root / "nan_intrinsics", "nan 0 32 24")
    _frames(root / "zero_intrinsics", "0 0 32 24")
    _frames(root / "far_centre", "40 40 1600 1600")
    _frames(root / "text_poses", poses="\n".join([GOOD_POSE, GOOD_POSE.replace("1.0", "one", 1), GOOD_POSE,
                                                  GOOD_POSE]))
    _frames(root / "bomb_frames")
    _bomb_png(root / "bomb_frames" / "0002.png")
    (root / "notafolder.txt").write_text("x")
    (root / "empty_model").mkdir()
    (root / "empty_model" / "manifest.json").write_text("{}")
    (root / "curve_folder_model").mkdir()
    (root / "curve_folder_model" / "manifest.json").write_text("{}")
    (root / "curve_folder_model" / "anytime_curve.json").mkdir()
    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(root / "ok.png")
    (root / "scan.csv").write_text(",".join(["2.0"] * 32))
    (root / "pairs.csv").write_text("ok.png,ok.png\n")
    from explorer.cost.devices import PROFILES_DIR
    tx2 = (PROFILES_DIR / "tx2.yaml").read_text()
    (root / "energy_typo.yaml").write_text(tx2.replace("fixed_j:", "fixd_j:").replace("name: tx2", "name: typo"))
    (root / "twice.yaml").write_text(tx2.replace("name: tx2", "name: twice\nname: again"))
    (root / "notjournal.log").write_text("this is not a journal\n")
    (root / "zeros.csv").write_text("deadline_ms\n0\n0\n0\n")
    _damaged_study(root / "damaged.log")
    (root / "edited.json").write_text(json.dumps({"format": "explorer-probe-results", "version": 1,
                                                  "bundle": {}, "device": {}, "conditions": {},
                                                  "layers": {"L0": float("nan")}, "stages": {}}))


RUN = ["run", "empty_model", "--image", "ok.png", "--scan", "scan.csv"]
BAD = {
    "binary space": ["space", "show", "random.bin"],
    "binary device": ["profile", "paper", "--device", "random.bin"],
    "alias bomb": ["space", "show", "bomb.yaml"],
    "nan intrinsics": ["train", "paper", "--supervision", "self", "--data", "frames:nan_intrinsics", "--steps", "1"],
    "zero intrinsics": ["train", "paper", "--supervision", "self", "--data", "frames:zero_intrinsics", "--steps", "1"],
    "principal point outside": ["data", "inspect", "--data", "frames:far_centre"],
    "frames on a file": ["data", "inspect", "--data", "frames:notafolder.txt"],
    "text in poses": ["train", "paper", "--supervision", "self", "--poses", "given", "--data", "frames:text_poses",
                      "--steps", "1"],
    "png bomb": ["train", "paper", "--supervision", "self", "--data", "frames:bomb_frames", "--steps", "1"],
    "run out jpg": RUN + ["--deadline", "5ms", "--out", "x.jpg"],
    "run out txt": RUN + ["--deadline", "5ms", "--out", "x.txt"],
    "run out unwritable": RUN + ["--deadline", "5ms", "--out", "/proc/nope/x.png"],
    "run out onto its image": RUN + ["--deadline", "5ms", "--out", "ok.png"],
    "drawing onto a frame": ["data", "inspect", "--data", "frames:bomb_frames", "--out", "bomb_frames/0001.png"],
    "drawing onto a listed frame": ["data", "inspect", "--data", "nyu:pairs.csv", "--out", "./ok.png"],
    "drawing into a data folder": ["data", "inspect", "--data", "frames:bomb_frames", "--out", "bomb_frames/new.png"],
    "drawing unwritable": ["data", "inspect", "--data", "synthetic:4:2", "--out", "/proc/nope/x.png"],
    "table unwritable": ["enumerate", "--space", "tiny", "--csv", "/proc/x.csv"],
    "curve onto a folder": ["curve", "curve_folder_model", "--device", "tx2"],
    "empty device": ["profile", "paper", "--device", ""],
    "energy key misspelt": ["profile", "paper", "--device", "energy_typo.yaml"],
    "profile key given twice": ["profile", "paper", "--device", "twice.yaml"],
    "image is a folder": ["run", "empty_model", "--image", "bomb_frames", "--scan", "scan.csv", "--deadline", "5ms"],
    "checkpoint is a folder": ["evaluate", "bomb_frames"],
    "text as a checkpoint": ["evaluate", "scan.csv"],
    "trace is a folder": ["anytime", "--path", "5:0.3", "--budget", "time:trace:bomb_frames"],
    "reference at 1x1": ["profile", "fastdepth", "--input-size", "1x1", "--device", "tx2"],
    "empty manifest": RUN + ["--deadline", "5ms"],
    "run threads": RUN + ["--deadline", "5ms", "--threads", "-3"],
    "run deadline 0": RUN + ["--deadline", "0ms"],
    "run deadline inf": RUN + ["--deadline", "inf"],
    "lr negative": ["train", "paper", "--lr", "-1"],
    "lr nan": ["train", "paper", "--lr", "nan"],
    "batch 0": ["train", "paper", "--batch-size", "0"],
    "size 63": ["train", "paper", "--train-size", "63x63"],
    "steps 0": ["train", "paper", "--steps", "0"],
    "supernet lr nan": ["supernet", "train", "--lr", "nan"],
    "inspect frames -5": ["data", "inspect", "--frames", "-5"],
    "evaluate frames 0": ["evaluate", "none.pt", "--frames", "0"],
    "curve frames 0": ["curve", "empty_model", "--frames", "0"],
    "curve deadlines 0": ["curve", "empty_model", "--deadlines", "0"],
    "trials -1": ["search", "--trials", "-1"],
    "sqlite in /proc": ["search", "--space", "tiny", "--storage", "sqlite:////proc/nope/x.db", "--trials", "1"],
    "not a journal": ["rescore", "--study", "s", "--storage", "journal:notjournal.log", "--device", "tx2",
                      "--budget", "time:uniform:33ms"],
    "damaged trial record": ["rescore", "--study", "dmg", "--storage", "journal:damaged.log", "--device", "tx2",
                             "--budget", "time:uniform:33ms"],
    "trace of zeros": ["enumerate", "--space", "paper", "--budget", "time:trace:zeros.csv"],
    "energy without energy": ["enumerate", "--space", "paper", "--device", "tx2-cpu", "--budget",
                              "energy:uniform:0.5J"],
    "nan loss": ["anytime", "--path", "5:nan", "--budget", "time:uniform:33ms"],
    "negative loss": ["anytime", "--path", "5:-0.5", "--budget", "time:uniform:33ms"],
    "study name": ["search", "--study", "a b<>", "--trials", "1"],
    "fit edited results": ["calibrate", "--fit", "edited.json", "--out", "p.yaml"],
    "export unknown study": ["export", "--study", "nope", "--out", "exported"],
    "trial of a checkpoint": ["export", "--checkpoint", "none.pt", "--trial", "3", "--out", "exported"],
    "self-supervision on frames": ["train", "paper", "--supervision", "self", "--data", "synthetic:48:16",
                                   "--steps", "1"],
    "missing supernet": ["search", "--space", "tiny", "--evaluator", "supernet", "--supernet", "missing.pt",
                         "--trials", "1"],
    # bounds: each of these ran for minutes, took gigabytes or started a process per unit
    "huge input size": ["profile", "paper", "--input-size", "65536x65536", "--device", "tx2"],
    "huge generated data": ["data", "inspect", "--data", "synthetic:50000000:10"],
    "endless deadlines": ["curve", "empty_model", "--deadlines", "100000000", "--device", "tx2"],
    "a thread per unit": RUN + ["--deadline", "5ms", "--threads", "100000"],
    "a thousand workers": ["search", "--workers", "1000", "--trials", "1"],
}


def _snapshot(*folders: Path) -> dict[str, str]:
    out = {}
    for folder in folders:
        for dirpath, dirnames, filenames in os.walk(folder):
            for name in dirnames + filenames:
                p = Path(dirpath) / name
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return out


@pytest.mark.slow
def test_each_mistake_is_one_line_exit_2_and_changes_nothing(tmp_path):
    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    cache.mkdir()
    _workspace(work)
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(cache)}
    before = _snapshot(work, cache)

    def run(args: list[str]):
        return subprocess.run([sys.executable, "-m", "explorer", *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=300)

    with ThreadPoolExecutor(max_workers=3) as pool:
        results = dict(zip(BAD, pool.map(run, BAD.values())))
    failures = []
    for name, res in results.items():
        lines = res.stderr.strip().splitlines()
        if res.returncode != 2 or len(lines) != 1 or "Traceback" in res.stderr:
            failures.append(f"{name}: exit {res.returncode}, stderr {res.stderr.strip()[-300:]!r}")
    assert not failures, "\n".join(failures)
    after = _snapshot(work, cache)
    assert after == before, f"created or changed: {sorted(set(after.items()) ^ set(before.items()))[:5]}"
