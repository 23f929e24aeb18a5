"""The GPU paths of supernet training, checked on the CPU: the device and backend each process picks,
the data held on the device, bf16 autocast, the GPU recipe and what progress shows."""

import dataclasses

import pytest
import torch

from conftest import TINY_DATA
from explorer.space import SearchSpace
from explorer.supernet import SupernetRecipe, default_path, train_supernet
from explorer.supernet import train as supernet_train

RECIPE = SupernetRecipe(steps=3, batch_size=8, input_size=(32, 32))


@pytest.fixture
def two_gpus(monkeypatch):
    """A machine with two CUDA devices, as far as the process picking its own can tell."""
    chosen = []
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "set_device", lambda d: chosen.append(torch.device(d)))
    monkeypatch.setenv("WORLD_SIZE", "1")
    return chosen


def test_each_local_process_takes_its_own_gpu(two_gpus, monkeypatch):
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert supernet_train._distributed(torch.device("cuda")) == (0, 1, torch.device("cuda", 1))
    assert two_gpus == [torch.device("cuda", 1)]
    monkeypatch.setenv("LOCAL_RANK", "3")     # more processes than GPUs: they share them round the ring
    assert supernet_train._distributed(torch.device("cuda"))[2] == torch.device("cuda", 1)
    assert supernet_train._distributed(torch.device("cuda", 0))[2] == torch.device("cuda", 0)   # as asked


def test_the_backend_follows_the_tensors_and_the_gpus_per_process(two_gpus, monkeypatch):
    assert supernet_train._backend(torch.device("cpu")) == "gloo"
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert supernet_train._backend(torch.device("cuda", 0)) == "nccl"
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")    # NCCL refuses two ranks on one GPU
    assert supernet_train._backend(torch.device("cuda", 0)) == "gloo"


def test_progress_shows_the_step_time_and_on_cuda_the_gpu_memory(monkeypatch):
    assert supernet_train._pace(0.25, torch.device("cpu")) == {"step_seconds": 0.25}
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device=None: 3 * 2**20)
    assert supernet_train._pace(0.25, torch.device("cuda", 0)) == {"step_seconds": 0.25, "gpu_memory_mb": 3.0}


def _weights(path):
    return torch.load(path, weights_only=True)["state_dict"]


def test_data_held_on_the_device_trains_the_same_supernet(tmp_path, monkeypatch):
    space = SearchSpace.from_yaml("tiny")
    shown = []
    resident = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "resident.pt",
                              progress=lambda s, n, r: shown.append(r))
    assert len(shown) == RECIPE.steps and all(r["step_seconds"] > 0 and "gpu_memory_mb" not in r for r in shown)
    import explorer.data.resident as resident_data
    monkeypatch.setattr(resident_data, "memory_budget", lambda device: 0)   # too big: a DataLoader
    loaded = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "loaded.pt")
    a, b = _weights(resident), _weights(loaded)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert torch.load(resident, weights_only=True)["history"] == torch.load(loaded, weights_only=True)["history"]


def test_bf16_autocast_trains_and_is_its_own_supernet(tmp_path):
    space = SearchSpace.from_yaml("tiny")
    amp = dataclasses.replace(RECIPE, amp=True)
    assert default_path(space, TINY_DATA, amp) != default_path(space, TINY_DATA, RECIPE)
    plain, mixed = (train_supernet(space, TINY_DATA, r, tmp_path / f"{r.amp}.pt") for r in (RECIPE, amp))
    history = torch.load(mixed, weights_only=True)["history"]
    assert all(0 < h["largest"] < 10 for h in history)
    a, b = _weights(plain), _weights(mixed)
    changed = [k for k in a if a[k].is_floating_point() and not torch.equal(a[k], b[k])]
    assert changed and all(torch.allclose(a[k], b[k], atol=0.05) for k in changed)


def test_files_made_before_the_amp_field_keep_their_cache_key():
    old = {k: v for k, v in SupernetRecipe().to_dict().items() if k != "amp"}
    assert "amp" not in SupernetRecipe.from_dict(old).identity()
    assert SupernetRecipe.from_dict(old) == SupernetRecipe()
    assert supernet_train.RECIPES["gpu"].identity()["amp"] is True


def test_the_gpu_recipe_is_one_flag_and_options_override_it(tmp_path, run_cli):
    out = tmp_path / "gpu.pt"
    code, _, err = run_cli("supernet", "train", "--space", "tiny", "--data", TINY_DATA, "--recipe", "gpu",
                           "--train-size", "32x32", "--steps", "1", "--batch-size", "8", "--out", out)
    assert code == 0, err
    recipe = torch.load(out, weights_only=True)["recipe"]
    assert recipe["amp"] is True and recipe["input_size"] == [32, 32] and recipe["batch_size"] == 8
    from explorer.cli import build_parser
    args = build_parser().parse_args(["supernet", "train", "--recipe", "gpu", "--no-amp"])
    from explorer.cli.training import supernet_recipe
    got = supernet_recipe(args)
    assert (got.input_size, got.batch_size, got.amp, got.steps) == ((224, 224), 64, False, 600)
    args = build_parser().parse_args(["supernet", "train"])
    assert supernet_recipe(args) == SupernetRecipe()    # the default recipe, as before the flag


def test_processes_that_would_resume_from_different_steps_are_refused(monkeypatch, tmp_path):
    import torch.distributed as dist
    from explorer.errors import UserError
    monkeypatch.setattr(dist, "get_world_size", lambda: 2)
    monkeypatch.setattr(dist, "all_gather_object", lambda out, obj: out.__setitem__(slice(None), [obj, obj]))
    supernet_train._check_same_start(5, tmp_path / "s.pt")           # every process at step 5: fine
    monkeypatch.setattr(dist, "all_gather_object", lambda out, obj: out.__setitem__(slice(None), [obj, 0]))
    with pytest.raises(UserError, match="every machine sees"):
        supernet_train._check_same_start(5, tmp_path / "s.pt")


def test_a_loss_read_one_step_late_still_stops_training_before_it_is_saved(tmp_path, monkeypatch):
    real = supernet_train._sandwich_step
    calls = []

    def step(*args):
        losses = real(*args)
        calls.append(1)
        return losses * float("nan") if len(calls) == 2 else losses
    monkeypatch.setattr(supernet_train, "_sandwich_step", step)
    out = tmp_path / "s.pt"
    with pytest.raises(FloatingPointError, match="at step 1"):
        train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, RECIPE, out, checkpoint_every=1)
    state = torch.load(out, weights_only=True)
    assert state["step"] == 1 and len(state["history"]) == 1
