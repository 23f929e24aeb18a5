"""Supernet training: the sandwich rule with in-place distillation, atomic checkpoints and resume,
a cache keyed by (space, data, recipe), and data parallelism under ``torchrun``.

Each step trains the largest subnet on the labels (its encoder depth turning over the space's depths,
``teacher_depths="cycle"``), then the smallest and a few random ones on the labels and on the
largest subnet's last exit (detached): every subnet keeps every exit, so every head is trained at
every step. Gradients of all subnets are summed before one optimizer step.

Data parallel: each of the W processes takes its share of the same global batch and the same
subnets; gradients are averaged with an all-reduce. BatchNorm statistics are per process (as in
DistributedDataParallel without SyncBatchNorm), so one process with ``micro_batches=W`` computes
the same update as W processes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import DataLoader

from explorer.errors import UserError
from explorer.space import Candidate, SearchSpace
from explorer.supernet.network import (Supernet, largest_candidate, random_training_subnet, smallest_candidate,
                                       space_identity, space_key)
from explorer.training.train import batch_row, lr_at, TrainConfig, multi_exit_loss

FORMAT = "anytime-explorer-supernet/1"
TEACHER_DEPTHS = ("cycle", "max")


@dataclass(frozen=True)
class SupernetRecipe:
    """AdamW with polynomial decay, batch ``batch_size`` per step (global, over all processes)."""

    steps: int = 600
    batch_size: int = 16
    input_size: tuple[int, int] = (64, 64)
    lr: float = 2e-3
    lr_end: float = 2e-4
    weight_decay: float = 1e-4
    random_subnets: int = 1          # besides the largest and the smallest, per step
    distill: float = 0.5             # weight of the largest subnet's output in the others' loss
    teacher_depths: str = "cycle"    # "cycle": the largest subnet's encoder depth turns over the space's; "max"
    micro_batches: int = 1           # per process; BatchNorm statistics are per micro-batch
    seed: int = 0

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["input_size"] = list(self.input_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SupernetRecipe":
        known = {f.name for f in dataclasses.fields(cls)}
        d = {"teacher_depths": "max", **{k: v for k, v in d.items() if k in known}}  # files made before "cycle"
        d["input_size"] = tuple(d["input_size"])
        return cls(**d)

    def identity(self) -> dict:
        """What changes the trained weights' meaning (how the work is spread does not)."""
        d = self.to_dict()
        d.pop("micro_batches")
        return d


def cache_key(space: SearchSpace, data: str, recipe: SupernetRecipe) -> str:
    text = json.dumps({"space": space_identity(space), "data": str(data), "recipe": recipe.identity()},
                      sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def default_path(space: SearchSpace, data: str, recipe: SupernetRecipe) -> Path:
    """Where the supernet of (space, data, recipe) is cached, next to the generated data."""
    from explorer.data.synthetic import cache_dir
    return cache_dir() / "supernets" / f"{space.name}-{cache_key(space, data, recipe)}.pt"


# -- files ----------------------------------------------------------------------------------------
def save(path: Path, net: Supernet, recipe: SupernetRecipe, data: str, step: int,
         optimizer: torch.optim.Optimizer | None, history: list[dict], seconds: float) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": FORMAT, "space": space_identity(net.space), "space_key": space_key(net.space),
             "space_name": net.space.name, "space_yaml": _space_text(net.space), "data": str(data),
             "recipe": recipe.to_dict(), "step": step, "complete": step >= recipe.steps,
             "state_dict": net.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
             "history": history, "seconds": seconds}
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)  # a kill never leaves a half-written file


def _space_text(space: SearchSpace) -> str:
    try:
        return Path(space.source).read_text()
    except OSError:
        return ""


def read(path: str | Path) -> dict:
    """A supernet file's contents; one clear error if it is missing, corrupt or not a supernet."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"supernet {p}: no such file (train one with `explorer supernet train`)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for truncated or foreign files
        raise UserError(f"supernet {p}: unreadable ({str(exc).splitlines()[0][:100]}); "
                        "delete it and train again") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise UserError(f"supernet {p}: not an anytime-explorer supernet file (format {FORMAT})")
    return state


def load(path: str | Path, space: SearchSpace | None = None, require_complete: bool = True
         ) -> tuple[Supernet, dict]:
    """The supernet in ``path``, checked against ``space`` (the space it must cover)."""
    state = read(path)
    if space is not None and state["space_key"] != space_key(space):
        raise UserError(f"supernet {path} was trained for space '{state['space_name']}' with other dimensions "
                        f"than '{space.name}': train one for this space (explorer supernet train --space "
                        f"{space.name}) or drop --supernet")
    if require_complete and not state.get("complete"):
        raise UserError(f"supernet {path} is only trained to step {state['step']} of "
                        f"{state['recipe']['steps']}: run `explorer supernet train` again to finish it")
    if space is None:
        space = SearchSpace.from_dict(_yaml(state["space_yaml"]), source=str(path))
    net = Supernet(space)
    try:
        net.load_state_dict(state["state_dict"])
    except RuntimeError as exc:
        raise UserError(f"supernet {path}: its tensors do not fit space '{space.name}' "
                        f"({str(exc).splitlines()[0][:100]})") from None
    return net, state


def _yaml(text: str):
    import yaml
    return yaml.safe_load(text)


# -- training -------------------------------------------------------------------------------------
def _distributed() -> tuple[int, int]:
    """(rank, world size), initialising torch.distributed when started by torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    import torch.distributed as dist
    if not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), dist.get_world_size()


def _subnet_loss(outs: list[torch.Tensor], target: torch.Tensor, teacher: torch.Tensor | None,
                 distill: float) -> torch.Tensor:
    loss, _ = multi_exit_loss([o.float() for o in outs], target)
    if teacher is None or distill <= 0:
        return loss
    soft = sum((o.float() - teacher).abs().mean() for o in outs[1:]) / (len(outs) - 1)
    return (1 - distill) * loss + distill * soft


def _teacher(largest: Candidate, space: SearchSpace, recipe: SupernetRecipe, step: int) -> Candidate:
    """The subnet trained on the labels alone and distilled from this step.

    With ``teacher_depths="max"`` it is the largest network, every step: the decoder and exit heads
    then learn on the deepest encoder's features and read shallower ones less well, and the supernet
    ranks deep encoders above shallow ones that retrain better. "cycle" turns the largest subnet's
    encoder depth over the space's depths, step by step, so each depth feeds the full decoder as often.
    """
    if recipe.teacher_depths == "max":
        return largest
    depths = sorted(space.encoder_blocks)
    return dataclasses.replace(largest, encoder_blocks=depths[step % len(depths)])


def train_supernet(space: SearchSpace, data: str, recipe: SupernetRecipe = SupernetRecipe(),
                   out: Path | None = None, device: torch.device | None = None,
                   progress: Callable[[int, int, dict], None] | None = None,
                   data_progress: Callable[[int, int], None] | None = None,
                   checkpoint_every: int = 100, max_steps: int | None = None) -> Path:
    """Trains (or resumes, or finds already trained) the supernet of (space, data, recipe) and
    returns its file. ``max_steps`` stops early (the file stays resumable)."""
    from explorer.data import open_dataset
    out = Path(out) if out else default_path(space, data, recipe)
    rank, world = _distributed()
    device = device or (torch.device("cuda", rank % torch.cuda.device_count()) if torch.cuda.is_available()
                        else torch.device("cpu"))
    if recipe.teacher_depths not in TEACHER_DEPTHS:
        raise UserError(f"teacher depths '{recipe.teacher_depths}': choose one of {', '.join(TEACHER_DEPTHS)}")
    if recipe.batch_size % (world * recipe.micro_batches):
        raise UserError(f"--batch-size {recipe.batch_size} must divide by processes x micro-batches "
                        f"({world} x {recipe.micro_batches})")
    torch.manual_seed(recipe.seed)  # every process starts from the same weights
    net = Supernet(space).to(device=device, memory_format=torch.channels_last)  # see train.image_batch
    opt = torch.optim.AdamW(net.parameters(), lr=recipe.lr, weight_decay=recipe.weight_decay)
    step, history, seconds = 0, [], 0.0
    if out.is_file():
        state = read(out)
        if state["space_key"] != space_key(space) or state["data"] != str(data) or \
                SupernetRecipe.from_dict(state["recipe"]).identity() != recipe.identity():
            raise UserError(f"supernet {out} exists for another space, data or recipe: give another --out, "
                            "or delete it")
        net.load_state_dict(state["state_dict"])
        if state.get("optimizer"):
            opt.load_state_dict(state["optimizer"])
        step, history, seconds = int(state["step"]), list(state.get("history", [])), float(state.get("seconds", 0))
    if step >= recipe.steps:
        return out
    train_set = open_dataset(data, "train", recipe.input_size, seed=recipe.seed, progress=data_progress)
    gen = torch.Generator().manual_seed(recipe.seed)
    loader = DataLoader(train_set, batch_size=recipe.batch_size, shuffle=True, generator=gen, drop_last=True)
    if len(loader) == 0:
        raise UserError(f"data {data}: {len(train_set)} training frames are fewer than --batch-size {recipe.batch_size}")
    largest, smallest = largest_candidate(space), smallest_candidate(space)
    per_rank = recipe.batch_size // world
    lr_cfg = TrainConfig(steps=recipe.steps, lr=recipe.lr, lr_end=recipe.lr_end)
    stop = recipe.steps if max_steps is None else min(recipe.steps, step + max_steps)
    epoch, t0 = step // len(loader), time.perf_counter()
    skip = step % len(loader)  # resume mid-epoch on the batches that were not seen
    while step < stop:
        train_set.epoch = epoch
        gen.manual_seed(recipe.seed + epoch)
        for i, batch in enumerate(loader):
            if i < skip:
                continue
            if step >= stop:
                break
            rng = random.Random(recipe.seed * 1_000_003 + step)  # the same subnets on every process
            subnets = [_teacher(largest, space, recipe, step), smallest] + \
                [random_training_subnet(space, rng) for _ in range(recipe.random_subnets)]
            for g in opt.param_groups:
                g["lr"] = lr_at(lr_cfg, step)
            net.train()
            opt.zero_grad(set_to_none=True)
            lo = rank * per_rank
            image, scan, depth = (batch[k][lo:lo + per_rank].to(device) for k in ("image", "scan", "depth"))
            image = image.contiguous(memory_format=torch.channels_last)
            row = batch_row(batch)
            losses = [0.0] * len(subnets)
            for chunk in range(recipe.micro_batches):
                part = slice(chunk * per_rank // recipe.micro_batches, (chunk + 1) * per_rank // recipe.micro_batches)
                teacher = None
                for j, cand in enumerate(subnets):
                    outs = net.forward_subnet(cand, image[part], scan[part], row)
                    loss = _subnet_loss(outs, depth[part], teacher, recipe.distill)
                    if j == 0:
                        teacher = outs[-1].detach().float()
                    (loss / recipe.micro_batches).backward()
                    losses[j] += float(loss.detach()) / recipe.micro_batches
            if not all(map(lambda v: v == v and abs(v) != float("inf"), losses)):
                raise FloatingPointError(f"supernet loss became {losses} at step {step}")
            if world > 1:
                import torch.distributed as dist
                for p in net.parameters():
                    if p.grad is not None:
                        dist.all_reduce(p.grad)
                        p.grad /= world
            opt.step()
            step += 1
            record = {"step": step, "largest": losses[0], "smallest": losses[1],
                      "random": sum(losses[2:]) / max(len(losses) - 2, 1)}
            history.append(record)
            if progress and rank == 0:
                progress(step, recipe.steps, record)
            if step % checkpoint_every == 0 and step < stop and rank == 0:
                save(out, net, recipe, data, step, opt, history, seconds + time.perf_counter() - t0)
        skip = 0
        epoch += 1
    if rank == 0:
        save(out, net, recipe, data, step, opt, history, seconds + time.perf_counter() - t0)
    if world > 1:
        import torch.distributed as dist
        dist.barrier()
    return out
