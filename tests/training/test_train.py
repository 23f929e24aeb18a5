
import pytest
import torch

from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import SearchSpace
from explorer.training.train import (TrainConfig, evaluate, load_encoder_weights, network_from_checkpoint,
                            train)
from explorer.errors import UserError
from conftest import TINY_DATA

CAND = list(SearchSpace.from_yaml("tiny").enumerate())[-1]


@pytest.fixture(scope="module")
def sets():
    return (open_dataset(TINY_DATA, "train", (32, 32)), open_dataset(TINY_DATA, "val", (32, 32)))


def test_training_lowers_every_exit(sets):
    torch.manual_seed(0)
    net = build_network(CAND)
    cfg = TrainConfig(steps=40, batch_size=8, input_size=(32, 32), lr=5e-3)
    result = train(net, *sets, cfg)
    first, last = result.history[:5], result.history[-5:]
    exits = [k for k in result.history[0] if k.startswith("exit_")]
    assert len(exits) == CAND.num_paths - 1
    for k in exits:
        assert sum(r[k] for r in last) < sum(r[k] for r in first), k
    assert list(result.metrics["path"]) == list(range(CAND.num_paths))
    assert result.images_per_second > 0


def test_checkpoint_resume_and_evaluate(tmp_path, sets):
    ckpt = tmp_path / "c.pt"
    cfg = TrainConfig(steps=6, batch_size=8, input_size=(32, 32))
    train(build_network(CAND), *sets, cfg, checkpoint=ckpt, checkpoint_every=3)
    net, state = network_from_checkpoint(ckpt)
    assert state["step"] == 6 and net.candidate == CAND
    # resuming a finished run trains no more steps
    again = train(build_network(CAND), *sets, cfg, checkpoint=ckpt)
    assert again.steps == 6 and again.history == []
    frame = evaluate(net, sets[1])
    assert set(["rmse", "rel", "delta1"]) <= set(frame.columns) and len(frame) == CAND.num_paths


def test_encoder_weights_loaded_from_a_state_dict(tmp_path):
    net = build_network(CAND)
    donor = build_network(CAND)
    f = tmp_path / "mobilenet.pt"
    torch.save(donor.stages["image_encoder"].state_dict(), f)
    n = load_encoder_weights(net, f)
    assert n > 0
    a, b = net.stages["image_encoder"].conv0[0].weight, donor.stages["image_encoder"].conv0[0].weight
    assert torch.equal(a, b)
    bad = tmp_path / "junk.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(UserError, match="unreadable"):
        load_encoder_weights(net, bad)


def test_micro_batches_compute_the_whole_batch_update(sets):
    """Without BatchNorm (whose statistics are per part by design) a batch trained in two parts takes
    the step the whole batch takes."""
    import copy

    def without_batchnorm(net):
        for name, module in list(net.named_modules()):
            for child, sub in list(module.named_children()):
                if isinstance(sub, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
                    setattr(module, child, torch.nn.Identity())
        return net
    torch.manual_seed(0)
    start = without_batchnorm(build_network(CAND))
    trained = {}
    for parts in (1, 2):
        net = copy.deepcopy(start)
        cfg = TrainConfig(steps=3, batch_size=8, input_size=(32, 32), optimizer="sgd", lr=0.05, micro_batches=parts)
        trained[parts] = (train(net, sets[0], [], cfg), net.state_dict())
    (whole, a), (split, b) = trained[1], trained[2]
    assert [r["loss"] for r in whole.history] == pytest.approx([r["loss"] for r in split.history], rel=1e-5)
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    assert any(not torch.equal(a[k], start.state_dict()[k]) for k in a)   # it trained
    assert "micro_batches" not in TrainConfig().to_dict()   # recipes stored before keep their keys


def test_a_batch_on_one_row_gives_that_row_and_a_slanted_one_each_columns_row():
    from explorer.training.train import batch_row
    level = {"scan_row": torch.tensor([16, 16]), "scan_rows": torch.full((2, 8), 16)}
    assert batch_row(level) == 16
    slanted = {"scan_row": torch.tensor([16, 17]), "scan_rows": torch.arange(16, 24).expand(2, 8)}
    assert torch.equal(batch_row(slanted), slanted["scan_rows"])
    assert batch_row({"scan_row": [12, 14, 20]}) == 14     # a batch of items without per-column rows


def test_self_distillation_pulls_the_early_exits_toward_the_last_and_leaves_the_last_alone():
    from explorer.training.train import self_distillation
    last = torch.full((2, 1, 4, 4), 3.0, requires_grad=True)
    early = torch.full((2, 1, 4, 4), 2.0, requires_grad=True)
    path0 = torch.zeros(2, 1, 4, 4)
    loss = self_distillation([path0, early, last])
    assert loss.item() == pytest.approx(1.0)
    loss.backward()
    assert last.grad is None and float(early.grad.sum()) < 0   # the early exit moves up toward the last
    assert float(self_distillation([path0, last.detach(), last.detach()])) == 0.0
    assert float(self_distillation([path0, last])) == 0.0          # one exit: nothing to learn from


def test_a_recipe_with_self_distillation_trains_and_keeps_its_weight():
    from explorer.study.config import SearchConfig
    with pytest.raises(UserError, match="--self-distill"):
        TrainConfig(self_distill=-1.0).validate()
    assert "self_distill" not in TrainConfig().to_dict()   # recipes stored before the field keep their keys
    cfg = TrainConfig(steps=2, batch_size=4, input_size=(32, 32), self_distill=0.5)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    net = build_network(next(SearchSpace.from_yaml("tiny").enumerate()))
    result = train(net, open_dataset(TINY_DATA, "train", (32, 32)), open_dataset(TINY_DATA, "val", (32, 32)), cfg,
                   val_limit=4)
    assert result.steps == 2 and torch.isfinite(torch.tensor(list(result.metrics["rmse"]))).all()
    # a study trains every network it compares with the same weight: proxy, finalists and baselines
    study = SearchConfig(study="s", self_distill=0.5)
    assert study.train_config().self_distill == study.finalist_config().self_distill == 0.5
