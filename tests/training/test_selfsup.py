import json

import numpy as np
import optuna
import pytest
import torch

from explorer.data import open_dataset
from explorer.errors import UserError
from explorer.model import build_network
from explorer.training.pose_net import PoseNet, transform_from_parameters
from explorer.study.search import SearchConfig, create_or_resume
from explorer.study.storage import load_study
from explorer.training.selfsup import SelfSupervisedLoss, photometric_error, reprojection_loss, warp
from explorer.space import SearchSpace
from explorer.training.train import TrainConfig, train

SEQ = "synthetic-seq:6:3"
CAND = list(SearchSpace.from_yaml("tiny").enumerate())[-1]


@pytest.fixture(scope="module")
def batch():
    ds = open_dataset(SEQ, "train", (64, 64))
    return torch.utils.data.default_collate([ds[i] for i in range(len(ds))])


def _reprojection(batch, depth, sources=None, automask=False):
    sources = sources or [batch["sources"][:, k] for k in range(2)]
    warped = [warp(s, depth, batch["K"], batch["pose"][:, k]) for k, s in enumerate(sources)]
    return reprojection_loss(batch["image"], sources, warped, automask)


def test_warping_with_true_depth_and_pose_reconstructs_the_target(batch):
    depth = batch["depth"]
    true, _ = _reprojection(batch, depth)
    assert float(true.mean()) < 0.012
    for wrong in (depth * 1.5, depth * 0.7, torch.full_like(depth, float(depth.mean()))):
        assert float(true.mean()) < 0.5 * float(_reprojection(batch, wrong)[0].mean())
    # the camera really moves: the frames differ far more before warping
    unwarped = torch.cat([photometric_error(batch["sources"][:, k], batch["image"]) for k in range(2)], 1)
    assert float(unwarped.min(1).values.mean()) > 4 * float(true.mean())


def test_automasking_removes_static_pixels(batch):
    # a patch that moves with the camera: identical in the target and both sources
    sources = [batch["sources"][:, k].clone() for k in range(2)]
    for s in sources:
        s[:, :, :20, :20] = batch["image"][:, :, :20, :20]
    _, mask = _reprojection(batch, batch["depth"], sources, automask=True)
    assert not mask[:, :, 2:18, 2:18].any()
    assert float(mask[:, :, 24:, 24:].float().mean()) > 0.8


def _scale_after_descent(batch, scan_loss: bool) -> float:
    """Depth and translation both scaled by exp(alpha): photometrically indistinguishable."""
    torch.manual_seed(0)
    batch = {k: v[:2] for k, v in batch.items()}
    alpha = torch.tensor(0.7, requires_grad=True)
    opt = torch.optim.Adam([alpha], lr=0.1)
    loss_fn = SelfSupervisedLoss("given", scan_loss)
    rot, trans = batch["pose"][..., :3], batch["pose"][..., 3:]
    for _ in range(30):
        s = alpha.exp()
        pose = torch.cat([rot, torch.cat([trans[:, :, :3] * s, trans[:, :, 3:]], 2)], 3)
        loss, _ = loss_fn([None, batch["depth"] * s], dict(batch, pose=pose), int(batch["scan_row"][0]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(alpha.detach())


def test_scan_term_fixes_the_scale(batch):
    assert abs(_scale_after_descent(batch, scan_loss=True)) < 0.1  # from 2x off to within 10%
    assert _scale_after_descent(batch, scan_loss=False) > 0.6  # no scale information without the scan


def test_pose_parameters_give_rigid_transforms():
    t = transform_from_parameters(torch.tensor([[0.0, 0.0, np.pi / 2]]), torch.tensor([[1.0, 2.0, 3.0]]))[0]
    assert torch.allclose(t[:3, :3] @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(t[:3, 3], torch.tensor([1.0, 2.0, 3.0]))
    out = PoseNet()(torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32))
    assert out.shape == (2, 4, 4) and torch.allclose(out[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(2, 4))


@pytest.mark.slow
def test_short_self_supervised_training_lowers_the_loss():
    train_set, val_set = open_dataset(SEQ, "train", (32, 32)), open_dataset(SEQ, "val", (32, 32))
    torch.manual_seed(0)
    cfg = TrainConfig(steps=25, batch_size=4, input_size=(32, 32), lr=5e-3, supervision="self")
    result = train(build_network(CAND), train_set, val_set, cfg)
    losses = [r["loss"] for r in result.history]
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])
    assert len(result.metrics) == CAND.num_paths
    with pytest.raises(UserError, match="needs sequence data"):
        train(build_network(CAND), open_dataset("synthetic:48:16", "val", (32, 32)), val_set, cfg)


def test_supervision_is_part_of_a_studys_identity(tmp_path):
    storage = optuna.storages.InMemoryStorage()
    cfg = SearchConfig(study="s", space="tiny", data=SEQ, supervision="self", baselines=False)
    create_or_resume(cfg.resolve(), storage)
    assert SearchConfig.from_dict(optuna.load_study(study_name="s", storage=storage).user_attrs["config"]).supervision == "self"
    assert cfg.train_config().supervision == "self"
    with pytest.raises(UserError, match="supervision='self'"):
        create_or_resume(SearchConfig(study="s", space="tiny", data=SEQ, baselines=False, evaluator="proxy").resolve(), storage)
    with pytest.raises(UserError, match="supervision 'weak'"):
        SearchConfig(study="t", space="tiny", supervision="weak").validate()
    with pytest.raises(UserError, match="needs sequence data"):
        SearchConfig(study="t", space="tiny", supervision="self").validate()
    # the supernet (the default with dense labels) is trained with labels: self-supervision trains alone
    assert SearchConfig(study="t", data=SEQ, supervision="self").evaluator == "proxy"
    assert SearchConfig(study="t").evaluator == "supernet"
    with pytest.raises(UserError, match="--evaluator proxy"):
        SearchConfig(study="t", space="tiny", data=SEQ, supervision="self", evaluator="supernet").validate()


@pytest.mark.slow
def test_cli_train_and_evaluate_self_supervised(run_cli, tmp_path):
    ckpt = tmp_path / "X.pt"
    code, _, err = run_cli("train", "paper", "--supervision", "self", "--data", "synthetic-seq:32:8", "--steps", "5",
                           "--train-size", "64x64", "--out", ckpt)
    assert code == 0, err
    assert torch.load(ckpt, weights_only=True)["train_config"]["supervision"] == "self"
    code, out, err = run_cli("evaluate", ckpt, "--data", "synthetic-seq:32:8", "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["supervision"] == "self" and res["median_scaling"] is False and len(res["paths"]) == 5
    assert all(np.isfinite(p["rmse"]) for p in res["paths"])
    # without the scan term the depth has no scale: evaluation median-scales it
    cfile = tmp_path / "cand.yaml"
    cfile.write_text(CAND.to_yaml())
    code, _, err = run_cli("train", cfile, "--supervision", "self", "--no-scan-loss", "--data", SEQ, "--steps", "1",
                           "--batch-size", "4", "--train-size", "32x32", "--out", tmp_path / "n.pt")
    assert code == 0, err
    code, out, _ = run_cli("evaluate", tmp_path / "n.pt", "--data", SEQ, "--json")
    assert code == 0 and json.loads(out)["median_scaling"] is True
    code, _, err = run_cli("train", cfile, "--supervision", "self", "--data", "synthetic:48:16", "--steps", "1")
    assert code == 2 and "needs sequence data" in err and len(err.strip().splitlines()) == 1


def test_cli_search_self_supervised_and_its_report(run_cli, tmp_path):
    code, out, err = run_cli("search", "--study", "ss", "--space", "tiny", "--data", SEQ, "--supervision", "self",
                             "--train-size", "32x32", "--input-size", "64x64", "--proxy-steps", "2",
                             "--batch-size", "4", "--trials", "1", "--timeout", "0", "--no-baselines",
                             "--evaluator", "proxy", "--finalists", "0", "--reports", tmp_path)
    assert code == 0, err
    study = load_study("ss", None, tmp_path)
    assert study.user_attrs["config"]["supervision"] == "self"
    assert any(t.state == optuna.trial.TrialState.COMPLETE for t in study.trials)
    assert "self supervision" in (tmp_path / "ss" / "report.html").read_text()
