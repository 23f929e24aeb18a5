"""Self-distillation in the supernet: every subnet's earlier exits also learn its own last exit's map,
detached, as a stand-alone network trained with --self-distill does."""

import pytest
import torch

from explorer.study.config import SearchConfig
from explorer.supernet.train import SupernetRecipe, _subnet_loss, cache_key
from explorer.space import SearchSpace
from explorer.training.train import self_distillation


def _outputs():
    torch.manual_seed(0)
    return [torch.rand(2, 1, 8, 8, requires_grad=True) for _ in range(4)]


def test_the_subnet_loss_adds_the_weighted_self_distillation_and_leaves_the_last_exit_alone():
    outs, target = _outputs(), torch.rand(2, 1, 8, 8) + 0.5
    plain = _subnet_loss(outs, target, None, 0.0)
    taught = _subnet_loss(outs, target, None, 0.0, self_distill=0.5)
    assert taught.item() == pytest.approx(plain.item() + 0.5 * self_distillation(outs).item())
    extra = taught - plain
    extra.backward()
    assert outs[-1].grad is None or torch.count_nonzero(outs[-1].grad) == 0   # the teacher is detached
    assert all(torch.count_nonzero(o.grad) > 0 for o in outs[1:-1])


def test_a_study_trains_its_supernet_with_its_self_distillation_and_caches_it_apart():
    assert SearchConfig(study="s", self_distill=0.5).supernet_recipe().self_distill == 0.5
    space = SearchSpace.from_yaml("tiny")
    plain, taught = SupernetRecipe(), SupernetRecipe(self_distill=0.5)
    assert "self_distill" not in plain.identity()   # supernets cached before the option keep their keys
    assert cache_key(space, "synthetic", plain) != cache_key(space, "synthetic", taught)
    assert SupernetRecipe.from_dict(plain.to_dict()) == plain
