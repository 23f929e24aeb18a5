"""The exit heads' refit: the least-squares output layer of every kind of head."""

import pytest
import torch

from explorer.model.exits import ExitHeadConfig
from explorer.study._refit import HeadRefit


@pytest.mark.parametrize("depth,residual,nearest,fuse", [
    (1, False, 1, 0), (2, False, 1, 0), (1, True, 1, 0), (2, True, 2, 0), (1, False, 2, 4), (2, True, 1, 4)])
def test_the_refit_recovers_the_output_layer_that_made_the_depths(depth, residual, nearest, fuse):
    torch.manual_seed(0)
    cfg = ExitHeadConfig(in_channels=6, depth=depth, width=5, upscale=4, lidar_channels=fuse, residual=residual,
                         nearest=nearest)
    teacher, student = cfg.build().eval(), cfg.build().eval()
    student.load_state_dict(teacher.state_dict())
    with torch.no_grad():   # the student differs from the teacher in its output layer only
        teacher.layers[-1].weight.normal_()
        teacher.layers[-1].bias.fill_(3.0)
    fit = HeadRefit(student)
    batches = []
    for _ in range(3):
        x = torch.randn(2, 6, 4, 8)
        extra = ([torch.randn(2, fuse, 8)] if fuse else []) + \
            ([torch.rand(2, 1, 16 * nearest, 32 * nearest)] if residual else [])
        with torch.no_grad():
            depth = teacher(x, *extra)
        depth[:, :, ::3] = 0     # rows without depth are left out of the fit
        batches.append((x, *extra))
        fit.add((x, *extra), depth)
    fit.apply()
    with torch.no_grad():
        for args in batches:
            assert (student(*args) - teacher(*args)).abs().max() < 1e-2
    assert torch.allclose(student.layers[-1].weight, teacher.layers[-1].weight, atol=1e-2)


def test_a_refit_without_depth_leaves_the_head_as_it_was():
    head = ExitHeadConfig(in_channels=3, depth=1, width=0, upscale=2).build().eval()
    before = [p.clone() for p in head.parameters()]
    fit = HeadRefit(head)
    fit.add((torch.randn(1, 3, 2, 2),), torch.zeros(1, 1, 4, 4))
    fit.apply()
    assert all(torch.equal(a, b) for a, b in zip(before, head.parameters()))
