"""A study on a robot's recording: a ROS bag in each of its three formats, supervised by its depth
topic or self-supervised, whose winner is exported and runs on the bag's own LiDAR scans."""

import json

import numpy as np
import pytest
from PIL import Image

from _bags import MOUNT, scene, write_bag

pytestmark = pytest.mark.slow

TINY = ["--space", "tiny", "--train-size", "32x32", "--input-size", "64x64", "--proxy-steps", "4", "--batch-size", "8",
        "--trials", "4", "--timeout", "0", "--supernet-steps", "4", "--finalists", "1", "--finalist-steps", "4",
        "--tune-steps", "2", "--no-report"]


@pytest.fixture(scope="module")
def recording():
    return scene(n=36, h=48, w=64)


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path / "cache"))


def _robot_inputs(tmp_path, sc):
    """What the robot's drivers hand over: a camera frame, the LiDAR's ranges, its mount and the camera."""
    Image.fromarray(sc.rgb[-1]).save(tmp_path / "frame.png")
    np.savetxt(tmp_path / "ranges.csv", sc.ranges[-1][None], delimiter=",")
    (tmp_path / "lidar.yaml").write_text("".join(f"{k}: {v}\n" for k, v in MOUNT.items()))
    K = sc.K
    (tmp_path / "intrinsics.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3", "mcap"])
def test_a_supervised_study_on_a_bag_exports_a_winner_that_runs_on_the_bags_scans(tmp_path, run_cli, recording, fmt):
    bag = write_bag(tmp_path / ("run.bag" if fmt == "ros1" else "run"), recording, fmt)
    code, out, err = run_cli("search", "--study", "robot", "--reports", tmp_path, "--data", f"rosbag:{bag}", *TINY)
    assert code == 0, err
    assert f"validation frames of rosbag:{bag}" in " ".join(out.split())
    code, _, err = run_cli("export", "--study", "robot", "--reports", tmp_path, "--out", tmp_path / "m")
    assert code == 0, err
    _robot_inputs(tmp_path, recording)
    code, out, err = run_cli("run", tmp_path / "m", "--image", tmp_path / "frame.png", "--scan", tmp_path / "ranges.csv",
                             "--lidar", tmp_path / "lidar.yaml", "--intrinsics", tmp_path / "intrinsics.txt",
                             "--deadline", "10s", "--out", tmp_path / "depth.npy", "--json")
    assert code == 0, err
    result = json.loads(out)
    depth = np.load(tmp_path / "depth.npy")
    errors = [m["rmse"] for m in json.loads((tmp_path / "m" / "manifest.json").read_text())["path_metrics"]]
    # every path ran; the one returned is the most accurate of them on the bag's validation frames
    assert result["completed_paths"] == len(errors) and result["path"] == int(np.argmin(errors))
    assert depth.shape == (64, 64) and np.isfinite(depth).all()


def test_a_self_supervised_study_on_a_bag_trains_on_its_frames_and_is_measured_on_its_depth(tmp_path, run_cli,
                                                                                         recording):
    bag = write_bag(tmp_path / "run", recording, "mcap")
    code, out, err = run_cli("search", "--study", "selfsup", "--reports", tmp_path, "--data", f"rosbag-seq:{bag}",
                             "--supervision", "self", "--no-baselines", *TINY)
    assert code == 0, err
    assert "winner" in out or "best searched candidate" in out


def test_a_study_on_a_bag_without_depth_scores_its_paths_by_the_motion_its_lidar_measures(tmp_path, run_cli):
    """No depth topic: each path's error is photometric, on validation frames posed by scan matching;
    the winner exports with those figures measured on its graphs and runs on the bag's scans."""
    import optuna
    from explorer.study.records import trial_record
    recording = scene(n=36, h=48, w=64, whole_room=True)   # a LiDAR that sees the side walls near the far one
    bag = write_bag(tmp_path / "run.bag", recording, "ros1", depth=None)
    code, out, err = run_cli("data", "inspect", "--data", f"rosbag-seq:{bag}", "--input-size", "48x64", "--json")
    facts = json.loads(out)
    assert code == 0 and facts["valid_depth_fraction"] == 0 and facts["posed_frames"] == facts["inspected"] > 0
    code, out, err = run_cli("search", "--study", "nodepth", "--reports", tmp_path, "--data", f"rosbag-seq:{bag}",
                             "--supervision", "self", "--no-baselines", *TINY)
    assert code == 0, err
    assert "photometric" in err and "photometric" in out
    study = optuna.load_study(study_name="nodepth", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(tmp_path / "nodepth" / "journal.log"))))
    scored = [trial_record(t) for t in study.trials if trial_record(t).path_metrics]
    assert scored and all(np.isfinite(r.losses_of("photometric")).all() for r in scored)
    assert all(r.error_metric == "photometric" for r in scored)
    code, _, err = run_cli("report", "--study", "nodepth", "--reports", tmp_path)
    assert code == 0, err
    assert "(photometric)" in (tmp_path / "nodepth" / "report.html").read_text()
    code, _, err = run_cli("export", "--study", "nodepth", "--reports", tmp_path, "--out", tmp_path / "m")
    assert code == 0, err
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert all(set(m) == {"photometric"} and m["photometric"] > 0 for m in manifest["path_metrics"])
    _robot_inputs(tmp_path, recording)
    code, out, err = run_cli("run", tmp_path / "m", "--image", tmp_path / "frame.png", "--scan", tmp_path / "ranges.csv",
                             "--lidar", tmp_path / "lidar.yaml", "--intrinsics", tmp_path / "intrinsics.txt",
                             "--deadline", "10s", "--out", tmp_path / "depth.npy")
    assert code == 0, err


def test_a_depth_metric_on_a_bag_without_depth_is_refused_before_the_study_exists(tmp_path, run_cli, recording):
    bag = write_bag(tmp_path / "run.bag", recording, "ros1", depth=None)
    code, _, err = run_cli("search", "--study", "nodepth", "--reports", tmp_path, "--data", f"rosbag-seq:{bag}",
                           "--supervision", "self", "--metric", "rmse", *TINY)
    assert code == 2 and "no depth to measure" in err and "--metric photometric" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "nodepth").exists()
    code, _, err = run_cli("search", "--study", "nodepth", "--reports", tmp_path, "--data", f"rosbag:{bag}", *TINY)
    assert code == 2 and "no depth topic" in err
