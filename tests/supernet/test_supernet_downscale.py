"""A network working at 1/k of its input trains and is scored on frames k times the training size, so
that it works at the training size as its twin at full size does: in the supernet's evaluation, the
proxy training and every training for deployment."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from conftest import TINY_DATA
from explorer.data import frames_for_downscale, open_dataset
from explorer.space import SearchSpace, load_yaml, resolve_space_path
from explorer.supernet import SupernetRecipe, train_supernet
from explorer.supernet import evaluators
from explorer.supernet.evaluators import ProxyEvaluator, SupernetEvaluator
from explorer.training import deployment
from explorer.training.deployment import DeploymentData, DeploymentRecipe, train_for_deployment
from explorer.training.train import PROXY, TrainResult, evaluate

SMALL = (32, 32)


@pytest.fixture(scope="module")
def space():
    return SearchSpace.from_dict({**load_yaml(resolve_space_path("tiny")), "downscale": [1, 2]}, source="both")


@pytest.fixture(scope="module")
def frames():
    return (open_dataset(TINY_DATA, "train", SMALL, train_augment=False),
            open_dataset(TINY_DATA, "val", SMALL, train_augment=False))


def test_the_frames_of_a_downscaled_network_are_the_same_frames_larger(frames):
    train, _ = frames
    larger = frames_for_downscale(train, 2)
    assert larger.input_size == (64, 64) and train.input_size == SMALL
    assert larger.frame_names() == train.frame_names()
    assert larger[0]["image"].shape[-2:] == (64, 64) and larger[0]["scan"].shape == (64,)
    assert frames_for_downscale(train, 1) is train


def test_the_supernet_scores_it_on_larger_frames_as_its_whole_network_does(space, frames, tmp_path):
    file = train_supernet(space, TINY_DATA, SupernetRecipe(steps=3, batch_size=8, input_size=SMALL), tmp_path / "s.pt")
    evaluator = SupernetEvaluator(file, space, *frames, torch.device("cpu"), calibration_images=8, batch_size=8)
    half = next(c for c in space.enumerate() if c.downscale == 2)
    twin = dataclasses.replace(half, downscale=1)
    got = evaluator(half).metrics
    calibration, validation = evaluator.downscaled[2]
    assert validation[0]["image"].shape[-2:] == (64, 64) and calibration[0]["image"].shape[-2:] == (64, 64)
    whole = evaluate(evaluator.network_of(half), validation)
    assert (got["rmse"] - whole["rmse"]).abs().max() < 1e-5
    assert list(got["path"]) == list(evaluator(twin).metrics["path"])
    # its weights are its twin's: the supernet has one set for both
    for a, b in zip(evaluator.supernet.extract(half).state_dict().values(),
                    evaluator.supernet.extract(twin).state_dict().values()):
        torch.testing.assert_close(a, b)


def _spy(monkeypatch, module):
    sizes = []

    def fake_train(net, train_set, val_set, *args, **kwargs):
        sizes.append(tuple(train_set.input_size))
        return TrainResult(None, [], 1.0, 1.0, 1)
    monkeypatch.setattr(module, "train", fake_train)
    return sizes


def test_proxy_training_and_training_for_deployment_use_frames_that_much_larger(space, frames, monkeypatch):
    half = next(c for c in space.enumerate() if c.downscale == 2)
    sizes = _spy(monkeypatch, evaluators)
    proxy = ProxyEvaluator(*frames, PROXY, torch.device("cpu"))
    proxy(half)
    proxy(dataclasses.replace(half, downscale=1))
    assert sizes == [(64, 64), SMALL]
    sizes = _spy(monkeypatch, deployment)
    deploy = open_dataset(TINY_DATA, "train", (96, 96))
    recipe = DeploymentRecipe(train=PROXY, deploy_size=(96, 96), tune_steps=2)
    from explorer.model import build_network
    train_for_deployment(build_network(half), DeploymentData(frames[0], deploy, deploy), recipe, None)
    assert sizes == [(64, 64), (96, 96)]   # then tuned where it is deployed, as it is
