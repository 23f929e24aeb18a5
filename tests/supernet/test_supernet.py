import dataclasses
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
import torch

from conftest import TINY_DATA
from explorer.data import open_dataset
from explorer.errors import UserError
from explorer.space import SearchSpace
from explorer.supernet import (Supernet, SupernetRecipe, largest_candidate, load_supernet, random_training_subnet,
                               train_supernet)
from explorer.supernet._stagewise import StageMemo, _StageResult
from explorer.supernet.evaluators import SupernetEvaluator, recalibrate_batchnorm
from explorer.training.train import multi_exit_loss

ROOT = Path(__file__).resolve().parents[2]
RECIPE = SupernetRecipe(steps=4, batch_size=8, input_size=(32, 32), random_subnets=1)


def _inputs(n=4, size=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, size, size, generator=g), torch.rand(n, size, generator=g) * 4 + 0.5


def _explorer(*args, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "explorer", *map(str, args)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


@pytest.fixture(scope="module")
def default_space():
    return SearchSpace.from_yaml("anytime_depth")


def test_largest_extracted_reproduces_the_supernet_exactly(default_space):
    net = Supernet(default_space)
    image, scan = _inputs()
    net.train()
    net(image, scan)  # move the BatchNorm statistics away from their initial values
    net.eval()
    with torch.no_grad():
        ref = net(image, scan)
        sub = net.extract(net.largest).eval()(image, scan)
    assert len(ref) == net.largest.num_paths
    assert all(torch.equal(a, b) for a, b in zip(ref, sub))


def test_residual_and_plain_exits_share_the_backbone_not_the_heads(default_space):
    net = Supernet(default_space)
    plain = dataclasses.replace(random_training_subnet(default_space, random.Random(5)), exit_residual=False)
    residual = dataclasses.replace(plain, exit_residual=True)
    a, b = net.subnet_tensors(plain), net.subnet_tensors(residual)
    assert set(a) == set(b)
    heads = {k for k in a if k.startswith(("stages.exit", "stages.lidar_exit"))}
    assert heads and all(a[k].data_ptr() != b[k].data_ptr() for k in heads if a[k].dim())
    assert all(torch.equal(a[k], b[k]) for k in set(a) - heads)
    image, scan = _inputs()
    net.eval()
    with torch.no_grad():
        sliced = net.forward_subnet(residual, image, scan)
        extracted = net.extract(residual).eval()(image, scan)
    assert all(torch.equal(x, y) for x, y in zip(sliced, extracted))


def test_a_smaller_candidate_is_a_slice_of_the_supernet(default_space):
    net = Supernet(default_space)
    cand = random_training_subnet(default_space, random.Random(3))
    sub = net.extract(cand)
    full = dict(net.slots.named_parameters())
    block = sub.stages["image_encoder"].blocks[1].pointwise[0].weight     # (out, in, 1, 1)
    wide = full["image_encoder.blocks.1.pointwise.0.weight"]
    assert block.shape[0] <= wide.shape[0] and torch.equal(block, wide[:block.shape[0], :block.shape[1]])
    head = sub.stages[f"exit_{cand.exits[-1]}"].layers[-1].weight
    slot = f"exit_{cand.exits[-1]}_d{cand.head_depth}" + ("_r" if cand.exit_residual else "")
    wide_head = full[f"{slot}.layers.{len(sub.stages[f'exit_{cand.exits[-1]}'].layers) - 1}.weight"]
    assert torch.equal(head, wide_head[:, :head.shape[1]])
    # an ordinary network: its weights are copies, training it leaves the supernet alone
    before = wide.clone()
    block.data.add_(1.0)
    assert torch.equal(wide, before)


def test_encoder_exits_and_lidar_exit_have_supernet_slots():
    space = SearchSpace.from_dict({
        "image_encoder": {"blocks": [6], "width_mult": [0.25, 0.5], "exits": [3, 5]},
        "lidar_encoder": {"depth": [4], "width": [8], "first": [False, True]},
        "ecu": {"enabled": [True], "band": [1, 3], "width": [16]},
        "decoder": {"widths": [[32], [16], [8], [8]]},
        "exits": {"optional": [0], "head_depth": [1, 2], "head_width": [8], "lidar_only": [False, True]}})
    net = Supernet(space).eval()
    image, scan = _inputs(2, 64)
    for cand in random.Random(0).sample(list(space.enumerate()), 6) + [net.largest]:
        with torch.no_grad():
            a = net.forward_subnet(cand, image, scan)
            b = net.extract(cand).eval()(image, scan)
        assert len(a) == cand.num_paths
        assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(a, b)), cand


def test_batchnorm_recalibration_changes_only_running_statistics(default_space):
    net = Supernet(default_space)
    sub = net.extract(random_training_subnet(default_space, random.Random(1)))
    before = {k: v.clone() for k, v in sub.state_dict().items()}
    image, scan = _inputs(8)
    recalibrate_batchnorm(sub, [{"image": image, "scan": scan, "depth": None, "scan_row": torch.tensor([16] * 8)}])
    after = sub.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.endswith(("running_mean", "running_var", "num_batches_tracked")) for k in changed)
    assert not sub.training
    with torch.no_grad():   # the exits' resize, skipped while recalibrating, is back
        assert all(o.shape[-2:] == (32, 32) for o in sub(image, scan))


def test_shared_encoder_features_give_the_same_evaluation(tmp_path):
    """Candidates of one width reuse that width's encoder run: same statistics, same metrics as
    running each candidate's own encoder; an encoder exit and every width covered."""
    space = SearchSpace.from_dict({
        "image_encoder": {"blocks": [4, 5], "width_mult": [0.25, 0.5], "exits": [3]},
        "lidar_encoder": {"depth": [4], "width": [8], "first": [False, True]},
        "ecu": {"enabled": [False, True], "band": [1], "width": [16]},
        "decoder": {"widths": [[32, 24], [16], [8, 4]]},
        "exits": {"optional": [0, 2], "head_depth": [1, 2], "head_width": [8], "residual": [False, True]}})
    file = train_supernet(space, TINY_DATA, SupernetRecipe(steps=3, batch_size=8, input_size=(32, 32)),
                          tmp_path / "s.pt")
    train = open_dataset(TINY_DATA, "train", (32, 32), train_augment=False)
    val = open_dataset(TINY_DATA, "val", (32, 32))
    args = (file, space, train, val, torch.device("cpu"))
    shared = SupernetEvaluator(*args, calibration_images=16, batch_size=8)
    alone = SupernetEvaluator(*args, calibration_images=16, batch_size=8, stagewise=False)
    candidates = random.Random(5).sample(list(space.enumerate()), 6)
    # and neighbours of the first: only the last decoder stage, or only the head depth, differs
    first = candidates[0]
    candidates += [dataclasses.replace(first, decoder_widths=first.decoder_widths[:-1] + (12 - first.decoder_widths[-1],)),
                   dataclasses.replace(first, head_depth=3 - first.head_depth, head_width=8 if first.head_depth == 1 else 0),
                   first]
    # residual heads of both depths too (a two-layer one recalibrates its statistics at full size)
    candidates += [dataclasses.replace(first, exit_residual=not first.exit_residual, head_depth=d, head_width=8 if d == 2 else 0)
                   for d in (1, 2)]
    assert {c.width_mult for c in candidates} == {0.25, 0.5} and any(c.encoder_exits for c in candidates)
    for cand in candidates:
        a, b = shared(cand), alone(cand)
        assert a.network is None    # stage by stage, no whole network was made; asked for, it is the same
        assert all(torch.allclose(x, y, atol=1e-5) for x, y in zip(shared.network_of(cand).state_dict().values(),
                                                                   b.network.state_dict().values())), cand
        assert list(a.metrics.columns) == list(b.metrics.columns) and list(a.metrics["path"]) == list(b.metrics["path"])
        assert (a.metrics["rmse"] - b.metrics["rmse"]).abs().max() < 1e-4, cand
    assert sorted(shared._encoders) == [0.25, 0.5]
    assert shared.memo.hits >= 2 * len(shared.supernet.stages_of(first)) - 4   # the repeat and its neighbours


def test_stage_memo_keeps_to_its_size():
    memo = StageMemo(max_bytes=100)
    for k in range(5):
        memo.put(k, _StageResult([], [], nbytes=40))
    assert list(memo.entries) == [3, 4] and memo.nbytes == 80
    assert memo.get(3) is not None and memo.get(0) is None
    memo.put(9, _StageResult([], [], nbytes=400))      # larger than the whole memo: not kept
    assert 9 not in memo.entries


def test_stage_memo_keeps_exits_beside_its_outputs():
    """An exit's metrics (no tensors) stay when the outputs that filled the memo are dropped."""
    memo = StageMemo(max_bytes=100)
    memo.put("exit", _StageResult(None, None, {"rmse": 0.5}))
    for k in range(5):
        memo.put(k, _StageResult([], [], nbytes=40))
    assert memo.get("exit").metrics == {"rmse": 0.5} and memo.get(0) is None and memo.nbytes == 80


def test_a_few_steps_lower_every_exit_loss_of_random_subnets(tmp_path):
    space = SearchSpace.from_yaml("tiny")
    data = open_dataset(TINY_DATA, "train", (32, 32), train_augment=False)
    batch = [data[i] for i in range(16)]
    image = torch.stack([b["image"] for b in batch])
    scan = torch.stack([b["scan"] for b in batch])
    depth = torch.stack([b["depth"] for b in batch])
    subnets = [random_training_subnet(space, random.Random(s)) for s in range(3)]

    def exit_losses(net):
        net.train()  # batch statistics, as during training
        with torch.no_grad():
            return [multi_exit_loss(net.forward_subnet(c, image, scan), depth)[1] for c in subnets]

    torch.manual_seed(0)
    start = exit_losses(Supernet(space))
    file = train_supernet(space, TINY_DATA, SupernetRecipe(steps=25, batch_size=8, input_size=(32, 32)),
                          tmp_path / "s.pt")
    end = exit_losses(load_supernet(file, space)[0])
    for a, b in zip(start, end):
        assert all(y < x for x, y in zip(a, b)), (a, b)


def test_resume_continues_exactly(tmp_path):
    space = SearchSpace.from_yaml("tiny")
    once = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "once.pt")
    part = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "twice.pt", stop_after_steps=2)
    assert torch.load(part, weights_only=True)["step"] == 2
    twice = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "twice.pt")
    a = torch.load(once, weights_only=True)["state_dict"]
    b = torch.load(twice, weights_only=True)["state_dict"]
    assert all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a if "running" not in k)


def test_progress_names_no_smallest_subnet_while_widths_stay_full(tmp_path):
    from explorer.cli._common import smallest_status
    seen = []
    file = train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, RECIPE, tmp_path / "s.pt",
                          progress=lambda step, total, record: seen.append(smallest_status(record)))
    assert RECIPE.shrink == 0.5 and len(seen) == RECIPE.steps
    assert seen[:2] == ["full widths"] * 2 and all(s.startswith("smallest ") for s in seen[2:])
    history = torch.load(file, weights_only=True)["history"]
    assert [h["smallest"] is None for h in history] == [True, True, False, False]


def test_a_long_step_count_is_still_saved_by_time(tmp_path, monkeypatch):
    """Checkpoints every N steps lose a slow machine's minutes: the file is also saved by time."""
    import explorer.supernet.train as supernet_train
    saved = []
    real = supernet_train.save
    monkeypatch.setattr(supernet_train, "save", lambda path, net, recipe, data, step, *a: saved.append(step) or
                        real(path, net, recipe, data, step, *a))
    space = SearchSpace.from_yaml("tiny")
    train_supernet(space, TINY_DATA, RECIPE, tmp_path / "s.pt", checkpoint_every=10**6, checkpoint_seconds=0.0)
    assert saved == list(range(1, RECIPE.steps + 1))   # every step, the last one as the run ends
    saved.clear()
    train_supernet(space, TINY_DATA, RECIPE, tmp_path / "t.pt", checkpoint_every=10**6, checkpoint_seconds=3600)
    assert saved == [RECIPE.steps]


def test_a_process_picks_its_accelerator_and_backend(monkeypatch):
    from explorer.supernet.train import _distributed
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert _distributed(torch.device("cpu")) == (0, 1, torch.device("cpu"))
    assert _distributed(None)[2].type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.slow
def test_kill_9_then_resume_training(tmp_path):
    out = tmp_path / "killed.pt"
    args = ["supernet", "train", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32",
            "--batch-size", "8", "--steps", "400", "--checkpoint-every", "2", "--out", out]
    proc = _explorer(*args, start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and not out.exists():
        time.sleep(0.2)
    assert out.exists(), proc.communicate(timeout=5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    step = torch.load(out, weights_only=True)["step"]
    assert 0 < step < 400
    resumed = _explorer(*[a if a != "400" else str(step + 3) for a in args])
    _, err = resumed.communicate(timeout=300)
    # another recipe (more steps) is another supernet: refused, the file is kept
    assert resumed.returncode == 2 and "another space, data or recipe" in err
    resumed = _explorer(*args[:-4], "--checkpoint-every", "1000", "--out", out, "--stop-after-steps", "3")
    _, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    state = torch.load(out, weights_only=True)
    assert state["step"] == step + 3 and len(state["history"]) == step + 3


def test_supernet_files_that_do_not_fit_are_one_line_exit_2(tmp_path, run_cli):
    space = SearchSpace.from_yaml("tiny")
    file = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "tiny.pt")
    code, _, err = run_cli("search", "--space", "paper", "--data", TINY_DATA, "--evaluator", "supernet", "--supernet", file,
                           "--reports", tmp_path, "--trials", "1")
    assert code == 2 and "trained for space 'tiny'" in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.pt"
    bad.write_bytes(file.read_bytes()[:1000])
    code, _, err = run_cli("search", "--space", "tiny", "--data", TINY_DATA, "--evaluator", "supernet", "--supernet", bad,
                           "--reports", tmp_path, "--trials", "1")
    assert code == 2 and "unreadable" in err and len(err.strip().splitlines()) == 1
    code, _, err = run_cli("supernet", "show", bad)
    assert code == 2
    code, _, err = run_cli("search", "--space", "tiny", "--evaluator", "proxy", "--supernet", file, "--reports", tmp_path)
    assert code == 2 and "--evaluator supernet" in err
    with pytest.raises(UserError):
        load_supernet(tmp_path / "absent.pt")


@pytest.mark.slow
def test_short_supernet_search_on_the_default_space(tmp_path):
    from explorer.study.search import SearchConfig, SearchRun, search
    cfg = SearchConfig(study="sn", data=TINY_DATA, train_size=(32, 32), batch_size=8, val_limit=16,
                       evaluator="supernet", supernet_steps=3, finalists=0, keep_weights=False)
    out = search(cfg.resolve(), SearchRun(n_trials=40, timeout_s=None, reports=tmp_path))
    done = [t for t in out.study.get_trials() if t.state == optuna.trial.TrialState.COMPLETE]
    assert not out.study.get_trials(states=(optuna.trial.TrialState.FAIL,))
    assert all(t.user_attrs["evaluator"]["evaluator"] == "supernet" for t in done)
    assert len({t.user_attrs["candidate_key"] for t in done}) >= 24
    assert {t.user_attrs.get("baseline") for t in done} >= {"paper", "paper-nee"}   # both are in the space
    assert "fastdepth" in out.study.user_attrs["baselines_not_estimated"]
    # the same study with the other evaluator would change what its values mean: refused
    import dataclasses
    with pytest.raises(UserError, match="evaluator"):
        search(dataclasses.replace(cfg, evaluator="proxy").resolve(), SearchRun(n_trials=1, reports=tmp_path))


@pytest.mark.slow
def test_two_gloo_processes_match_one_process(tmp_path):
    common = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--batch-size", "8", "--steps", "3"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    ddp = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                          "--master_port", str(29500 + os.getpid() % 1000), "-m", "explorer", "supernet", "train",
                          *common, "--out", str(tmp_path / "ddp.pt")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert ddp.returncode == 0, ddp.stderr[-2000:]
    one = subprocess.run([sys.executable, "-m", "explorer", "supernet", "train", *common, "--micro-batches", "2",
                          "--out", str(tmp_path / "one.pt")], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert one.returncode == 0, one.stderr[-2000:]
    a = torch.load(tmp_path / "ddp.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "one.pt", weights_only=True)["state_dict"]
    params = [k for k in a if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    diff = torch.cat([(a[k] - b[k]).abs().flatten() for k in params])
    # summation order differs, and Adam turns the rare near-zero gradient into up to lr-sized noise
    # per step; processes that did not share their gradients would differ almost everywhere
    assert float((diff > 1e-5).float().mean()) < 1e-2 and float(diff.max()) < 3 * 3 * 2e-3
    moved = torch.load(tmp_path / "one.pt", weights_only=True)
    assert moved["step"] == 3


def test_largest_candidate_covers_the_space(default_space):
    big = largest_candidate(default_space)
    assert big.encoder_blocks == max(default_space.encoder_blocks)
    assert set(big.exits[:-1]) == set(default_space.optional_exits) | set(default_space.required_exits)


@pytest.mark.parametrize("teacher, depths", [("cycle", [2, 3, 2, 3]), ("max", [3, 3, 3, 3])])
def test_the_label_trained_subnet_turns_over_encoder_depths(tmp_path, monkeypatch, teacher, depths):
    space = SearchSpace.from_yaml("tiny")
    first = []
    original = Supernet.forward_subnet

    def spy(self, candidate, *args, **kw):
        if not first or len(first[-1]) == 3:   # a new step: label-trained, smallest, random
            first.append([])
        first[-1].append(candidate)
        return original(self, candidate, *args, **kw)

    monkeypatch.setattr(Supernet, "forward_subnet", spy)
    recipe = dataclasses.replace(RECIPE, teacher_depths=teacher)
    train_supernet(space, TINY_DATA, recipe, tmp_path / "s.pt")
    assert [step[0].encoder_blocks for step in first] == depths
    assert all(step[0].decoder_widths == largest_candidate(space).decoder_widths for step in first)


def test_supernet_files_made_before_cycling_read_as_max():
    old = {k: v for k, v in RECIPE.to_dict().items() if k != "teacher_depths"}
    assert SupernetRecipe.from_dict(old).teacher_depths == "max"
    assert SupernetRecipe.from_dict(RECIPE.to_dict()).teacher_depths == "cycle"


def test_an_unknown_teacher_depths_is_refused(tmp_path):
    recipe = dataclasses.replace(RECIPE, teacher_depths="deepest")
    with pytest.raises(UserError, match="cycle, max"):
        train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, recipe, tmp_path / "s.pt")
    assert not (tmp_path / "s.pt").exists()


def test_candidates_share_their_stages_weightless_modules_and_still_compute_their_own_networks(default_space):
    net = Supernet(default_space).eval()
    rng = random.Random(3)
    image, scan = _inputs(2)
    first = random_training_subnet(default_space, rng)
    other = next(c for c in (random_training_subnet(default_space, rng) for _ in range(1000))
                 if c != first and (c.encoder_blocks, c.width_mult) == (first.encoder_blocks, first.width_mult))
    plans = [net._plan(c)[0] for c in (first, other)]
    shared = [n for n in plans[0].stages if n in plans[1].stages and plans[0].stages[n] is plans[1].stages[n]]
    assert "image_encoder" in shared    # built once, for both
    for cand in (first, other, first):
        with torch.no_grad():
            a = net.forward_subnet(cand, image, scan)
            b = net.extract(cand).eval()(image, scan)
        assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(a, b)), cand


def test_a_stage_extracted_alone_is_that_stage_of_the_extracted_network(default_space):
    net = Supernet(default_space)
    cand = random_training_subnet(default_space, random.Random(4))
    whole = net.extract(cand)
    for spec in net.stages_of(cand):
        alone, inside = net.extract_stage(spec).state_dict(), whole.stages[spec.name].state_dict()
        assert alone.keys() == inside.keys() and all(torch.equal(alone[k], inside[k]) for k in alone), spec.name


def test_a_damaged_or_incomplete_supernet_file_is_one_line_exit_2(tmp_path, run_cli):
    """torch.load checks no checksum: a weight or an optimizer moment overwritten on disk, an empty
    file, or a file with only its format are refused before any candidate is estimated."""
    space = SearchSpace.from_yaml("tiny")
    file = train_supernet(space, TINY_DATA, RECIPE, tmp_path / "tiny.pt")
    state = torch.load(file, weights_only=True)
    weights = dict(state["state_dict"])
    name = next(k for k, v in weights.items() if v.is_floating_point() and v.numel() > 4)
    weights[name] = torch.rand_like(weights[name])                # random values, all finite
    moments = state["optimizer"]["state"][0]
    damaged = {"weights": {**state, "state_dict": weights},
               "optimizer": {**state, "optimizer": {**state["optimizer"], "state": {
                   **state["optimizer"]["state"], 0: {**moments, "exp_avg": moments["exp_avg"] * 2}}}},
               "no digest, a NaN": {**{k: v for k, v in state.items() if k != "digest"},
                                    "state_dict": {**weights, name: weights[name] * float("nan")}},
               "only its format": {"format": state["format"]}}
    for what, content in damaged.items():
        bad = tmp_path / f"{what}.pt"
        torch.save(content, bad)
        for args in (("supernet", "show", bad), ("search", "--space", "tiny", "--data", TINY_DATA, "--evaluator",
                                                  "supernet", "--supernet", bad, "--reports", tmp_path, "--trials", "1")):
            code, _, err = run_cli(*args)
            assert code == 2 and len(err.strip().splitlines()) == 1, (what, err)
            assert ("damaged" if what != "only its format" else "incomplete") in err, (what, err)
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    code, _, err = run_cli("supernet", "show", empty)
    assert code == 2 and "unreadable" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "tiny-search").exists()
    code, _, err = run_cli("supernet", "show", file)
    assert code == 0, err
