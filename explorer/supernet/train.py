"""Supernet training: the sandwich rule, atomic checkpoints and resume, a cache keyed by (space,
data, recipe), and data parallelism under ``torchrun``.

Each step trains the largest subnet (its encoder depth turning over the space's depths,
``teacher_depths="cycle"``), the smallest and a few random ones on the labels: every subnet keeps
every exit, so every head is trained at every step. With ``distill`` > 0 the others also learn the
largest subnet's last exit (in-place distillation); by default they do not, because the supernet
then ranked stand-alone results better (bench_fidelity, 2 seeds each). Gradients of
all subnets are summed before one optimizer step.

Progressive shrinking (``shrink``, as in Once-for-All): for the first half of the steps every subnet
keeps the full widths (encoder depths, exits, LiDAR paths and heads still vary), and the smallest
subnet's place goes to a random one; then every width trains. Without it the supernet ranked wide
networks too low and narrow ones too high: the channels only wide subnets use trained on a fraction
of the steps, while the smallest trained every step. With it, it ranked stand-alone results better
(bench_fidelity, 2 seeds each).

On a GPU each stage of a subnet is replayed from a CUDA graph (``recipe.cuda_graphs``,
``explorer.supernet._graphs``): the default recipe's kernels are too small for anything but their
launches to set the step's time.

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

from explorer.data import open_dataset
from explorer.data.resident import training_batches
from explorer.data.synthetic import cache_dir
from explorer.errors import UserError
from explorer.files import check_writable_folder, remove_dead_scratch, writing_atomically
from explorer.processes import StopAtStep
from explorer.space import Candidate, SearchSpace, check_size
from explorer.supernet._graphs import StageGraphs
from explorer.supernet.network import (Supernet, head_kinds, largest_candidate, random_training_subnet,
                                       smallest_candidate, space_identity, space_key, with_head_kind)
from explorer.training.train import TrainConfig, adamw, batch_row, lr_at, self_distillation

FORMAT = "anytime-explorer-supernet/1"
TEACHER_DEPTHS = ("cycle", "max")
HEAD_KINDS = ("rotate", "cover", "random")


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
    distill: float = 0.0             # weight of the largest subnet's output in the others' loss
    self_distill: float = 0.0        # weight of each subnet's own last exit (detached) in its earlier exits' loss
    teacher_depths: str = "cycle"    # "cycle": the largest subnet's encoder depth turns over the space's; "max"
    micro_batches: int = 1           # per process; BatchNorm statistics are per micro-batch
    seed: int = 0
    amp: bool = False                # bf16 autocast of the forward passes (the GPU recipe's)
    head_kinds: str = "rotate"       # which subnet trains which kind of exit head (see _subnets)
    shrink: float = 0.5              # this fraction of the steps first trains full widths only (see _subnets)
    cuda_graphs: bool = True         # on CUDA, each stage replayed from a CUDA graph (supernet/_graphs.py)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["input_size"] = list(self.input_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SupernetRecipe":
        known = {f.name for f in dataclasses.fields(cls)}
        # files made before these fields trained the way they were then
        d = {"teacher_depths": "max", "head_kinds": "random", "shrink": 0.0,
             **{k: v for k, v in d.items() if k in known}}
        d["input_size"] = tuple(d["input_size"])
        return cls(**d)

    def identity(self) -> dict:
        """What changes the trained weights' meaning (how the work is spread does not)."""
        d = self.to_dict()
        d.pop("micro_batches")
        d.pop("cuda_graphs")
        if not d["amp"]:     # files and caches made before the field keep their keys
            d.pop("amp")
        if d["head_kinds"] == "random":
            d.pop("head_kinds")
        if not d["shrink"]:
            d.pop("shrink")
        if not d["self_distill"]:
            d.pop("self_distill")
        return d


#: named recipes (``explorer supernet train --recipe``): the default fits a laptop's CPU; "gpu" trains
#: at the deployment resolution, with batches that keep a GPU's cores busy, under bf16 autocast
RECIPES = {"default": SupernetRecipe(),
           "gpu": SupernetRecipe(batch_size=64, input_size=(224, 224), amp=True)}


def cache_key(space: SearchSpace, data: str, recipe: SupernetRecipe) -> str:
    text = json.dumps({"space": space_identity(space), "data": str(data), "recipe": recipe.identity()},
                      sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def default_path(space: SearchSpace, data: str, recipe: SupernetRecipe) -> Path:
    """Where the supernet of (space, data, recipe) is cached, next to the generated data."""
    return cache_dir() / "supernets" / f"{space.name}-{cache_key(space, data, recipe)}.pt"


# -- files ----------------------------------------------------------------------------------------
#: a supernet in training is saved at least this often (seconds), whatever its steps take
CHECKPOINT_SECONDS = 60.0


def save(path: Path, net: Supernet, recipe: SupernetRecipe, data: str, step: int,
         optimizer: torch.optim.Optimizer | None, history: list[dict], seconds: float) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": FORMAT, "space": space_identity(net.space), "space_key": space_key(net.space),
             "space_name": net.space.name, "space_yaml": _space_text(net.space), "data": str(data),
             "recipe": recipe.to_dict(), "step": step, "complete": step >= recipe.steps,
             "state_dict": net.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
             "history": history, "seconds": seconds}
    state["digest"] = tensors_digest(state["state_dict"], state["optimizer"])
    remove_dead_scratch(path.parent, only_for=path)   # what a save killed midway left (tens of MB)
    with writing_atomically(path) as f:   # a kill never leaves a half-written file, a full disk no scratch
        torch.save(state, f)


def _space_text(space: SearchSpace) -> str:
    try:
        return Path(space.source).read_text()
    except OSError:
        return ""


#: what every supernet file holds
_KEYS = ("space_key", "space_name", "space_yaml", "recipe", "step", "state_dict")


def tensors_digest(*trees) -> str:
    """SHA-256 over every tensor in ``trees`` (nested dicts and lists), names and bytes: what a file's
    weights and optimizer state were saved as (``torch.load`` checks no checksum of its own)."""
    digest = hashlib.sha256()

    def walk(node, name: str) -> None:
        if isinstance(node, torch.Tensor):
            digest.update(name.encode())
            digest.update(node.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
        elif isinstance(node, dict):
            for key in sorted(node, key=str):
                walk(node[key], f"{name}/{key}")
        elif isinstance(node, (list, tuple)):
            for i, item in enumerate(node):
                walk(item, f"{name}/{i}")
    for i, tree in enumerate(trees):
        walk(tree, str(i))
    return digest.hexdigest()


def read(path: str | Path) -> dict:
    """A supernet file's contents; one clear error if it is missing, corrupt, damaged (its tensors no
    longer match the digest they were saved with, or, in a file saved without one, not finite) or not a
    supernet."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"supernet {p}: no such file (train one with `explorer supernet train`)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for truncated, empty or foreign files
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:100]
        raise UserError(f"supernet {p}: unreadable ({why}); delete it and train again") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise UserError(f"supernet {p}: not an anytime-explorer supernet file (format {FORMAT})")
    missing = [k for k in _KEYS if k not in state]
    if missing or not isinstance(state["state_dict"], dict):
        raise UserError(f"supernet {p}: incomplete file (no {', '.join(missing) or 'weights'}); delete it and "
                        "train again")
    damaged = "its tensors do not match the digest they were saved with" if "digest" in state and \
        tensors_digest(state["state_dict"], state.get("optimizer")) != state["digest"] else \
        next((f"non-finite weights in {k}" for k, v in state["state_dict"].items()
              if v.is_floating_point() and not bool(torch.isfinite(v).all())), None)
    if damaged:
        raise UserError(f"supernet {p}: damaged ({damaged}); delete it and train again")
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
def _distributed(accelerator: torch.device | None) -> tuple[int, int, torch.device]:
    """(rank, world size, the device this process trains on). Under torchrun, torch.distributed is
    initialised with the backend the accelerator needs (NCCL for CUDA tensors, gloo for CPU ones), and a
    CUDA accelerator without an index becomes this process's own GPU, ``cuda:LOCAL_RANK`` (made the
    current device, so that NCCL and every kernel see one GPU per process). More processes on a machine
    than it has GPUs share them, and then reduce through gloo: NCCL refuses two ranks on one GPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if accelerator is None:
        accelerator = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if accelerator.type == "cuda":
        if accelerator.index is None:
            local = int(os.environ.get("LOCAL_RANK", "0"))
            accelerator = torch.device("cuda", local % max(torch.cuda.device_count(), 1))
        torch.cuda.set_device(accelerator)
    if world <= 1:
        return 0, 1, accelerator
    import torch.distributed as dist
    if not dist.is_initialized():
        dist.init_process_group(_backend(accelerator))
    return dist.get_rank(), dist.get_world_size(), accelerator


def _backend(accelerator: torch.device) -> str:
    """NCCL where each local process has a GPU of its own, else gloo (CPU tensors, or GPUs shared)."""
    if accelerator.type != "cuda":
        return "gloo"
    local = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")))
    return "nccl" if local <= torch.cuda.device_count() else "gloo"


def _exits_l1(outs: list[torch.Tensor], target: torch.Tensor) -> torch.Tensor:
    """``multi_exit_loss`` with equal weights, without reading each exit's loss back to the host (a
    wait for the GPU per exit), over the exits stacked (every exit is at full resolution): a handful of
    kernels whatever the number of exits."""
    valid = target > 0
    n = valid.sum().clamp(min=1)
    stacked = torch.stack(outs[1:]).float()
    return torch.where(valid, (stacked - target).abs(), 0.0).sum() / (n * (len(outs) - 1))


def _subnet_loss(outs: list[torch.Tensor], target: torch.Tensor, teacher: torch.Tensor | None,
                 distill: float, self_distill: float = 0.0) -> torch.Tensor:
    """A subnet's loss: L1 of every exit on the labels, the largest subnet's last exit (``teacher``) mixed
    in with weight ``distill``, and the subnet's own last exit taught to its earlier ones with weight
    ``self_distill`` (as ``explorer train --self-distill`` does: a network's early exits learn its best map)."""
    loss = _exits_l1(outs, target)
    if teacher is not None and distill > 0:
        soft = sum((o.float() - teacher).abs().mean() for o in outs[1:]) / (len(outs) - 1)
        loss = (1 - distill) * loss + distill * soft
    if self_distill > 0:
        loss = loss + self_distill * self_distillation([o.float() for o in outs])
    return loss


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


def _subnets(largest: Candidate, smallest: Candidate, space: SearchSpace, recipe: SupernetRecipe, step: int,
             rng: random.Random) -> list[Candidate]:
    """This step's subnets: the teacher, the smallest, ``recipe.random_subnets`` random ones.

    Each kind of exit head (depth x residual) has its own weights. The largest and the smallest
    subnets always train two kinds; with ``head_kinds="random"`` a random subnet draws its kind, so
    the other kinds train about a quarter of the steps each (their heads see 4x fewer updates).
    "cover" gives the random subnets those other kinds in turn: each trains at least every other step.
    "rotate" hands the kinds in turn to every subnet of the step, the teacher and the smallest too: each
    kind then trains on every kind of backbone (with 3 subnets a step, 3 steps in 4; with 4, every step),
    where the others train a kind on one backbone alone (the largest's residual depth-2 heads, the
    smallest's plain depth-1 heads).

    In the first ``recipe.shrink`` of the steps every subnet has the full widths, and a random one
    takes the smallest's place (progressive shrinking).
    """
    randoms = [random_training_subnet(space, rng) for _ in range(recipe.random_subnets)]
    if _shrinking(recipe, step):   # progressive shrinking: widths stay full at first
        smallest, *randoms = [_full_width(c, largest) for c in [random_training_subnet(space, rng)] + randoms]
    subnets = [_teacher(largest, space, recipe, step), smallest] + randoms
    every = head_kinds(space)
    if recipe.head_kinds == "rotate":
        return [with_head_kind(c, space, *every[(step * len(subnets) + j) % len(every)])
                for j, c in enumerate(subnets)]
    if recipe.head_kinds == "cover":
        kinds = [k for k in every if k not in {(c.head_depth, c.exit_residual) for c in (largest, smallest)}]
        if kinds:
            subnets[2:] = [with_head_kind(c, space, *kinds[(step * len(randoms) + j) % len(kinds)])
                           for j, c in enumerate(randoms)]
    return subnets


def _shrinking(recipe: SupernetRecipe, step: int) -> bool:
    """Whether step ``step`` (from 0) trains full widths only (progressive shrinking's first phase)."""
    return step < recipe.shrink * recipe.steps


def _full_width(candidate: Candidate, largest: Candidate) -> Candidate:
    """``candidate`` with every width of ``largest`` (its depths, exits, LiDAR path and heads kept)."""
    widths = dict(width_mult=largest.width_mult, decoder_widths=largest.decoder_widths,
                  head_width=largest.head_width if candidate.head_depth == 2 else 0,
                  # heads sized per position: the largest's there (0, as head_width, where it has none of its own)
                  encoder_head_width=largest.head("encoder")[1], ecu_head_width=largest.head("ecu")[1])
    if candidate.ecu:
        widths.update(lidar_width=largest.lidar_width, ecu_width=largest.ecu_width)
    return dataclasses.replace(candidate, **widths)


def train_supernet(space: SearchSpace, data: str, recipe: SupernetRecipe = SupernetRecipe(),
                   out: Path | None = None, accelerator: torch.device | None = None,
                   progress: Callable[[int, int, dict], None] | None = None,
                   data_progress: Callable[[int, int], None] | None = None,
                   checkpoint_every: int = 100, stop_after_steps: int | None = None,
                   checkpoint_seconds: float = CHECKPOINT_SECONDS, deadline: float | None = None) -> Path:
    """Trains (or resumes, or finds already trained) the supernet of (space, data, recipe) and
    returns its file. ``accelerator``: the torch device to train on (default: this process's GPU
    where there is one, else the CPU). ``stop_after_steps`` ends this call after that many more steps,
    short of ``recipe.steps``, with the file saved to resume from; so does reaching ``deadline`` (a
    time.time(), one process only: a search's time limit). The file is saved every
    ``checkpoint_every`` steps and at least every ``checkpoint_seconds``: a killed run loses at most that."""
    out = Path(out) if out else default_path(space, data, recipe)
    rank, world, accelerator = _distributed(accelerator)
    _check_recipe(recipe, world, space)
    if deadline is not None and world > 1:
        raise ValueError("a deadline would stop the processes at different steps: give it to one process only")
    torch.manual_seed(recipe.seed)  # every process starts from the same weights
    net = Supernet(space).to(device=accelerator, memory_format=torch.channels_last)  # see train.image_batch
    opt = adamw(net.parameters(), recipe.lr, recipe.weight_decay)
    step, history, seconds = _resume(out, space, data, recipe, net, opt)
    if world > 1:
        _check_same_start(step, out)
    if step >= recipe.steps:
        return out
    if rank == 0:   # its saves, tried before any training (a search's supernet goes to the cache)
        check_writable_folder(out.parent, "supernet", "give --out, or ANYTIME_EXPLORER_CACHE, a folder you can write")
    train_set = open_dataset(data, "train", recipe.input_size, seed=recipe.seed, progress=data_progress)
    gen = torch.Generator().manual_seed(recipe.seed)
    loader = training_batches(train_set, recipe.batch_size, gen, accelerator)   # on the device where it fits
    if len(loader) == 0:
        raise UserError(f"data {data}: {len(train_set)} training frames are fewer than --batch-size {recipe.batch_size}")
    largest, smallest = largest_candidate(space), smallest_candidate(space)
    lr_cfg = TrainConfig(steps=recipe.steps, lr=recipe.lr, lr_end=recipe.lr_end)
    stop = recipe.steps if stop_after_steps is None else min(recipe.steps, step + stop_after_steps)
    epoch, t0 = step // len(loader), time.perf_counter()
    saved = t0
    ledger = _Ledger(history, progress if rank == 0 else None, recipe.steps, accelerator)
    graphs = StageGraphs() if recipe.cuda_graphs and accelerator.type == "cuda" else None
    skip = step % len(loader)  # resume mid-epoch on the batches that were not seen
    # Ctrl-C or SIGTERM ends training at the end of a step, with the supernet reached saved (resumed from)
    held = StopAtStep(_saving(out, net, recipe, data, opt, ledger, history, seconds, t0), out, step, recipe.steps,
                      what="supernet's weights", active=world == 1)   # several processes stop together: not held
    with held:
        while step < stop:
            train_set.epoch = epoch
            gen.manual_seed(recipe.seed + epoch)
            for i, batch in enumerate(loader):
                if i < skip:
                    continue
                if deadline is not None and time.time() >= deadline:
                    stop = step
                if step >= stop:
                    break
                rng = random.Random(recipe.seed * 1_000_003 + step)  # the same subnets on every process
                subnets = _subnets(largest, smallest, space, recipe, step, rng)
                for g in opt.param_groups:
                    g["lr"] = lr_at(lr_cfg, step)
                shrinking = _shrinking(recipe, step)
                step += 1
                ledger.add(step, _sandwich_step(net, opt, batch, subnets, recipe, accelerator, rank, world, graphs),
                           shrinking)
                now = time.perf_counter()
                if (step % checkpoint_every == 0 or now - saved >= checkpoint_seconds) and step < stop and rank == 0:
                    ledger.settle()
                    save(out, net, recipe, data, step, opt, history, seconds + now - t0)
                    saved = time.perf_counter()
                held.check(step)   # a Ctrl-C during the step: the supernet saved, then stopped
            skip = 0
            epoch += 1
    ledger.settle()
    if rank == 0:
        save(out, net, recipe, data, step, opt, history, seconds + time.perf_counter() - t0)
    if world > 1:
        import torch.distributed as dist
        dist.barrier()
    return out


def _saving(out: Path, net: Supernet, recipe: SupernetRecipe, data: str, opt: torch.optim.Optimizer, ledger: "_Ledger",
            history: list[dict], seconds: float, t0: float) -> Callable[[int], None]:
    """The save of the supernet at a step, for a stop in mid-run (:class:`~explorer.processes.StopAtStep`)."""
    def save_at(step: int) -> None:
        ledger.settle()
        save(out, net, recipe, data, step, opt, history, seconds + time.perf_counter() - t0)
    return save_at


def _check_same_start(step: int, out: Path) -> None:
    """Every process must resume from the same step: a checkpoint on one machine's disk alone would
    start the others over, and the processes would train different networks (or wait on each other)."""
    import torch.distributed as dist
    steps: list = [None] * dist.get_world_size()
    dist.all_gather_object(steps, step)
    if len(set(steps)) > 1:
        raise UserError(f"supernet {out}: the processes found it at steps {sorted(set(steps))}; give --out a "
                        "path that every machine sees (shared storage)")


class _Ledger:
    """The steps' records, read back from the device one step late: step N's losses are read once step
    N+1 is queued, so that the host prepares the next step (its subnets, their slices, the kernel
    launches) while the GPU still runs this one. A non-finite loss stops training one step later."""

    def __init__(self, history: list[dict], progress: Callable[[int, int, dict], None] | None, total: int,
                 accelerator: torch.device) -> None:
        self.history, self.progress, self.total, self.accelerator = history, progress, total, accelerator
        self.pending: tuple[int, torch.Tensor, bool] | None = None
        self.last = time.perf_counter()

    def add(self, step: int, losses: torch.Tensor, shrinking: bool = False) -> None:
        """Step ``step`` is queued with ``losses`` (one per subnet, on the device; ``shrinking``: the
        second subnet is a random full-width one, not the smallest): the step before it is read."""
        self.settle()
        self.pending = (step, losses, shrinking)

    def settle(self) -> None:
        """Reads the pending step (waiting for the device), checks and records it."""
        if self.pending is None:
            return
        (step, losses, shrinking), self.pending = self.pending, None
        values = losses.tolist()
        if not all(map(lambda v: v == v and abs(v) != float("inf"), values)):
            raise FloatingPointError(f"supernet loss became {values} at step {step - 1}")
        # while shrinking, no subnet is the smallest: the record says so rather than mislabel one
        others = values[1:] if shrinking else values[2:]
        record = {"step": step, "largest": values[0], "smallest": None if shrinking else values[1],
                  "random": sum(others) / max(len(others), 1)}
        self.history.append(record)
        now = time.perf_counter()
        if self.progress:
            self.progress(step, self.total, {**record, **_pace(now - self.last, self.accelerator)})
        self.last = now


def _pace(step_seconds: float, accelerator: torch.device) -> dict:
    """What progress shows besides the losses: the step's wall time and, on CUDA, the most GPU memory
    the process has held (MiB)."""
    pace = {"step_seconds": step_seconds}
    if accelerator.type == "cuda":
        pace["gpu_memory_mb"] = torch.cuda.max_memory_allocated(accelerator) / 2**20
    return pace


def _check_recipe(recipe: SupernetRecipe, world: int, space: SearchSpace) -> None:
    check_size(recipe.input_size, space.max_working_stride, "--train-size")
    if not 0 <= recipe.distill <= 1:
        raise UserError(f"--distill {recipe.distill}: give a weight between 0 (off, the default) and 1")
    if not 0 <= recipe.self_distill <= 10:
        raise UserError(f"--self-distill {recipe.self_distill:g}: give a weight between 0 (off) and 10")
    if not 0 <= recipe.shrink < 1:
        raise UserError(f"--shrink {recipe.shrink}: give the fraction of the steps trained at full widths first, "
                        "from 0 (off) to below 1")
    if recipe.head_kinds not in HEAD_KINDS:
        raise UserError(f"head kinds '{recipe.head_kinds}': choose one of {', '.join(HEAD_KINDS)}")
    if recipe.teacher_depths not in TEACHER_DEPTHS:
        raise UserError(f"teacher depths '{recipe.teacher_depths}': choose one of {', '.join(TEACHER_DEPTHS)}")
    if recipe.batch_size % (world * recipe.micro_batches):
        raise UserError(f"--batch-size {recipe.batch_size} must divide by processes x micro-batches "
                        f"({world} x {recipe.micro_batches})")


def _resume(out: Path, space: SearchSpace, data: str, recipe: SupernetRecipe, net: Supernet,
            opt: torch.optim.Optimizer) -> tuple[int, list[dict], float]:
    """(step, history, seconds of training) of the file ``out``, its weights and optimizer state
    loaded into ``net`` and ``opt``; (0, [], 0.0) if there is no file yet. A file for another space,
    data or recipe is refused rather than overwritten."""
    if not out.is_file():
        return 0, [], 0.0
    state = read(out)
    if state["space_key"] != space_key(space) or state["data"] != str(data) or \
            SupernetRecipe.from_dict(state["recipe"]).identity() != recipe.identity():
        raise UserError(f"supernet {out} exists for another space, data or recipe: give another --out, "
                        "or delete it")
    net.load_state_dict(state["state_dict"])
    if state.get("optimizer"):
        opt.load_state_dict(state["optimizer"])
    return int(state["step"]), list(state.get("history", [])), float(state.get("seconds", 0))


def _sandwich_step(net: Supernet, opt: torch.optim.Optimizer, batch: dict, subnets: list[Candidate],
                   recipe: SupernetRecipe, accelerator: torch.device, rank: int, world: int,
                   graphs: StageGraphs | None = None) -> torch.Tensor:
    """One optimizer step on process ``rank``'s share of ``batch``: every subnet's gradients summed
    (and averaged over the ``world`` processes), the first subnet's last exit distilled into the
    others; the subnets' losses, left on the device (no wait for the GPU here: :class:`_Ledger` reads
    them once the next step is queued); ``recipe.amp`` runs the forward passes under bf16 autocast (no
    loss scaling: bf16 has float32's range); ``graphs``: the stages replayed from CUDA graphs (autocast's
    weight cache off: a graph must not keep a cast copy from its capture)."""
    per_rank = recipe.batch_size // world
    if not net.training:   # train() walks every module of the supernet: a step's worth of host time on a GPU
        net.train()
    opt.zero_grad(set_to_none=True)
    lo = rank * per_rank
    image, scan, depth = (batch[k][lo:lo + per_rank].to(accelerator, non_blocking=True)
                          for k in ("image", "scan", "depth"))
    image = image.contiguous(memory_format=torch.channels_last)
    row = batch_row(batch)
    losses = torch.zeros(len(subnets), dtype=torch.float64, device=accelerator)
    for chunk in range(recipe.micro_batches):
        part = slice(chunk * per_rank // recipe.micro_batches, (chunk + 1) * per_rank // recipe.micro_batches)
        teacher = None
        for j, cand in enumerate(subnets):
            with torch.autocast(accelerator.type, dtype=torch.bfloat16, enabled=recipe.amp,
                                cache_enabled=graphs is None):
                outs = net.forward_subnet(cand, image[part], scan[part], row, graphs)
                loss = _subnet_loss(outs, depth[part], teacher, recipe.distill, recipe.self_distill)
            if j == 0 and recipe.distill > 0:   # a copy: a graph's output is overwritten by its next replay
                teacher = outs[-1].detach().float().clone()
            (loss / recipe.micro_batches).backward()
            losses[j] += loss.detach().double() / recipe.micro_batches
    if graphs is not None:
        graphs.gradients_to()
    if world > 1:
        _average_gradients(net, world)
    opt.step()
    if graphs is not None:
        graphs.clear()
    return losses


#: gradients are averaged over processes in flat buckets of about this many bytes: one collective per
#: bucket rather than one per parameter tensor (hundreds of small all-reduces a step)
BUCKET_BYTES = 25 << 20


def _average_gradients(net: Supernet, world: int) -> None:
    """Averages the gradients over the ``world`` processes. Every process trained the same subnets, so
    the same parameters have gradients everywhere and the buckets line up."""
    import torch.distributed as dist
    buckets: list[list[torch.Tensor]] = [[]]
    size = 0
    for g in (p.grad for p in net.parameters() if p.grad is not None):
        nbytes = g.numel() * g.element_size()
        if buckets[-1] and (size + nbytes > BUCKET_BYTES or g.dtype != buckets[-1][0].dtype):
            buckets.append([])
            size = 0
        buckets[-1].append(g)
        size += nbytes
    for bucket in filter(None, buckets):
        flat = torch.cat([g.reshape(-1) for g in bucket])
        dist.all_reduce(flat)
        flat /= world
        offset = 0
        for g in bucket:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()
