import pytest
import torch

import explorer.training.depth_hints as depth_hints
from explorer.data import open_dataset
from explorer.training.depth_hints import HintedDataset, compute_hints, with_hints
from explorer.training.selfsup import hint_loss
from explorer.errors import UserError
from explorer.model.exits import interpolate_scan
from explorer.training.train import TrainConfig
from explorer.study.storage import load_study

SEQ = "synthetic-seq:6:3"


def _rmse(depth: torch.Tensor, gt: torch.Tensor) -> float:
    valid = gt > 0
    return float(torch.stack([((d[v] - g[v]) ** 2).mean().sqrt() for d, g, v in zip(depth, gt, valid)]).mean())


@pytest.mark.slow
def test_hints_are_closer_to_the_true_depth_than_path_0():
    ds = open_dataset(SEQ, "train", (64, 64))
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    hints = compute_hints(batch, steps=150)
    assert hints.shape == batch["depth"].shape and bool((hints > 0).all())
    path0 = interpolate_scan(batch["scan"], 64)
    assert _rmse(hints, batch["depth"]) < 0.9 * _rmse(path0, batch["depth"])


def test_hint_loss_pulls_only_where_the_hint_explains_the_frames_better():
    depth, hint = torch.full((1, 1, 2, 2), 2.0), torch.full((1, 1, 2, 2), 3.0)
    worse, better = torch.full_like(depth, 0.2), torch.full_like(depth, 0.1)
    assert float(hint_loss(depth, hint, depth_error=better, hint_error=worse)) == 0.0
    assert float(hint_loss(depth, hint, depth_error=worse, hint_error=better)) == pytest.approx(float(torch.log1p(torch.tensor(1.0))))
    half = torch.tensor([[[[0.1, 0.3], [0.1, 0.3]]]])
    assert float(hint_loss(depth, hint, depth_error=half, hint_error=torch.full_like(depth, 0.2))) == \
        pytest.approx(float(torch.log1p(torch.tensor(1.0))) / 2)


def test_hints_are_computed_once_then_read_from_the_cache(tmp_path, monkeypatch):
    ds = open_dataset(SEQ, "train", (32, 32))
    hinted = with_hints(ds, steps=3, cache=tmp_path)
    files = list(tmp_path.glob("hints-*.pt"))
    assert len(files) == 1 and not list(tmp_path.glob("*.tmp*"))
    item = hinted[1]
    assert item["hint"].shape == item["depth"].shape and set(ds[1]) < set(item)
    hinted.epoch = 3  # the training loop sets it on the data set it gets: it must reach the real one
    assert ds.epoch == 3 and hinted.max_depth == ds.max_depth
    monkeypatch.setattr(depth_hints, "compute_hints", lambda *a, **k: pytest.fail("hints computed again"))
    again = with_hints(ds, steps=3, cache=tmp_path)
    assert torch.equal(again.hints, hinted.hints)
    # another recipe is another file
    monkeypatch.setattr(depth_hints, "compute_hints", lambda batch, steps: torch.ones_like(batch["depth"]))
    assert isinstance(with_hints(ds, steps=4, cache=tmp_path), HintedDataset)
    assert len(list(tmp_path.glob("hints-*.pt"))) == 2


def test_depth_hints_need_self_supervision_with_given_poses():
    with pytest.raises(UserError, match="--poses given"):
        TrainConfig(supervision="self", poses="net", hints=True).validate()
    with pytest.raises(UserError, match="--supervision self or mixed"):
        TrainConfig(supervision="supervised", poses="given", hints=True).validate()
    TrainConfig(supervision="mixed", poses="given", hints=True).validate()


def test_cli_train_with_depth_hints(run_cli, tmp_path):
    ckpt = tmp_path / "h.pt"
    code, _, err = run_cli("train", "paper", "--supervision", "self", "--poses", "given", "--depth-hints",
                           "--data", SEQ, "--steps", "2", "--batch-size", "3", "--train-size", "32x32", "--out", ckpt)
    assert code == 0, err
    assert torch.load(ckpt, weights_only=True)["train_config"]["hints"] is True
    code, _, err = run_cli("train", "paper", "--supervision", "self", "--depth-hints", "--data", SEQ,
                           "--steps", "1", "--train-size", "32x32", "--out", tmp_path / "x.pt")
    assert code == 2 and "--poses given" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.pt").exists()


def test_cli_search_with_depth_hints_records_them(run_cli, tmp_path):
    import optuna
    code, _, err = run_cli("search", "--study", "hs", "--space", "tiny", "--data", SEQ, "--supervision", "self",
                           "--poses", "given", "--depth-hints", "--train-size", "32x32", "--input-size", "64x64",
                           "--proxy-steps", "2", "--batch-size", "3", "--trials", "1", "--timeout", "0",
                           "--no-baselines", "--evaluator", "proxy", "--finalists", "0", "--reports", tmp_path)
    assert code == 0, err
    study = load_study("hs", None, tmp_path)
    assert study.user_attrs["config"]["hints"] is True and study.user_attrs["config"]["poses"] == "given"
    assert any(t.state == optuna.trial.TrialState.COMPLETE for t in study.trials)
    assert "self supervision with depth hints" in (tmp_path / "hs" / "report.html").read_text()
    # resuming without hints would change what a trial's value means
    code, _, err = run_cli("search", "--study", "hs", "--space", "tiny", "--data", SEQ, "--supervision", "self",
                           "--poses", "given", "--train-size", "32x32", "--input-size", "64x64",
                           "--proxy-steps", "2", "--batch-size", "3", "--trials", "1", "--timeout", "0",
                           "--no-baselines", "--evaluator", "proxy", "--finalists", "0", "--reports", tmp_path)
    assert code == 2 and "hints" in err and len(err.strip().splitlines()) == 1
