"""Multi-exit training: one loss over all exits, the paper's full recipe and a short proxy recipe
for search, checkpoints and resume, per-path evaluation."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pandas as pd
import torch
from torch.utils.data import DataLoader

from explorer.data import parse_data_spec
from explorer.data.resident import training_batches
from explorer.errors import UserError
from explorer.files import remove_dead_scratch, writing_atomically
from explorer.metrics import PHOTOMETRIC, MetricAverager, batch_depth_metrics, depth_metrics
from explorer.model import AnytimeDepthNet, build_network
from explorer.processes import StopAtStep
from explorer.space import Candidate
from explorer.training.depth_hints import HintedDataset, with_hints
from explorer.training.selfsup import POSE_SOURCES, SUPERVISIONS, SelfSupervisedLoss, photometric_score


@dataclass(frozen=True)
class TrainConfig:
    """SGD with polynomial decay from ``lr`` to ``lr_end`` (the paper: 0.05 -> 0.02, weight decay
    1e-4, batch 96, fp16), or AdamW for the proxy recipe. ``exit_weights`` weigh the exits' losses
    (None = equal). ``supervision``: "supervised" (L1 on dense depth), "self" (photometric
    reprojection between neighbouring frames, :mod:`explorer.training.selfsup`; needs sequence data) or
    "mixed" (both); ``poses``: "net" (a pose network trained jointly) or "given" (the data's);
    ``scan_loss``: an L1 term on the scan row that gives self-supervision metric scale; ``hints``:
    pull each exit toward a per-frame depth optimised on the same loss where it explains the frames
    better (:mod:`explorer.training.depth_hints`; needs ``poses="given"``)."""

    steps: int = 300
    batch_size: int = 16
    input_size: tuple[int, int] = (112, 112)
    optimizer: str = "adamw"
    lr: float = 2e-3
    lr_end: float = 2e-4
    momentum: float = 0.9
    weight_decay: float = 1e-4
    exit_weights: tuple[float, ...] | None = None
    amp: bool = True                  # mixed precision where the hardware has it (CUDA)
    seed: int = 0
    eval_every: int = 0               # 0 = only at the end
    supervision: str = "supervised"
    poses: str = "net"
    scan_loss: bool = True
    hints: bool = False               # depth hints for self-supervision (explorer.training.depth_hints)
    micro_batches: int = 1            # a step's batch in this many parts, one after another (BatchNorm per part)
    self_distill: float = 0.0         # weight of the last exit's detached map in every earlier exit's loss

    @property
    def metric(self) -> bool:
        """Whether the trained depth is in metres; if not, evaluation median-scales it."""
        return self.supervision != "self" or self.scan_loss or self.poses == "given"

    def validate(self) -> None:
        if self.supervision not in SUPERVISIONS:
            raise UserError(f"supervision '{self.supervision}': use one of {', '.join(SUPERVISIONS)}")
        if self.poses not in POSE_SOURCES:
            raise UserError(f"poses '{self.poses}': use one of {', '.join(POSE_SOURCES)}")
        if not 0.0 <= self.self_distill <= 10.0:
            raise UserError(f"--self-distill {self.self_distill:g}: give a weight between 0 (off) and 10")
        if self.hints and (self.supervision == "supervised" or self.poses != "given"):
            raise UserError("--depth-hints needs --supervision self or mixed with --poses given: hints are "
                            "optimised with the data's camera motion")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["input_size"] = list(self.input_size)
        d["exit_weights"] = list(self.exit_weights) if self.exit_weights else None
        for key, default in (("micro_batches", 1), ("self_distill", 0.0)):
            if d[key] == default:   # recipes stored before the field keep their keys
                del d[key]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        d["input_size"] = tuple(d["input_size"])
        if d.get("exit_weights"):
            d["exit_weights"] = tuple(d["exit_weights"])
        return cls(**d)


#: Short training for ranking candidates during a search (reduced resolution, few hundred steps).
PROXY = TrainConfig()
#: The paper's recipe (Sec. 5.1): SGD, lr 0.05 -> 0.02 polynomial, wd 1e-4, batch 96, fp16.
PAPER = TrainConfig(steps=20000, batch_size=96, input_size=(224, 224), optimizer="sgd", lr=0.05,
                    lr_end=0.02, weight_decay=1e-4, eval_every=1000)
RECIPES = {"proxy": PROXY, "paper": PAPER}


def resolve_accelerator(accelerator: str = "auto") -> torch.device:
    """The torch device that ``--accelerator`` names: auto (CUDA when PyTorch sees a GPU, else the
    CPU), cpu or cuda."""
    if accelerator == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if accelerator == "cuda" and not torch.cuda.is_available():
        raise UserError("--accelerator cuda: torch sees no CUDA device here (use cpu or auto)")
    if accelerator not in ("cpu", "cuda"):
        raise UserError(f"unknown accelerator '{accelerator}': use auto, cpu or cuda")
    return torch.device(accelerator)


def multi_exit_loss(outputs: list[torch.Tensor], target: torch.Tensor,
                    weights: tuple[float, ...] | None = None) -> tuple[torch.Tensor, list[float]]:
    """Weighted L1 over valid pixels of every exit (path 0 has no parameters and is skipped)."""
    valid = target > 0
    n = valid.sum().clamp(min=1)
    losses = [((o - target).abs() * valid).sum() / n for o in outputs[1:]]
    w = weights or (1.0,) * len(losses)
    if len(w) != len(losses):
        raise UserError(f"exit_weights has {len(w)} values but the network has {len(losses)} exits")
    total = sum(wi * li for wi, li in zip(w, losses)) / sum(w)
    return total, [float(li.detach()) for li in losses]


def self_distillation(outputs: list[torch.Tensor]) -> torch.Tensor:
    """Mean L1, over every pixel, of each exit before the last against the last exit's map, detached:
    the early exits learn from the network's own best answer (dense, where labels may be sparse or
    absent), and the last exit is not pulled toward them."""
    exits = outputs[1:]
    if len(exits) < 2:
        return exits[-1].sum() * 0.0
    teacher = exits[-1].detach()
    return torch.stack([(o - teacher).abs().mean() for o in exits[:-1]]).mean()


def _training_loss(cfg: TrainConfig, selfsup, outs: list[torch.Tensor], batch: dict, accelerator: torch.device
                   ) -> tuple[torch.Tensor, list[float]]:
    outs = [o.float() for o in outs]
    loss, per_exit = _task_loss(cfg, selfsup, outs, batch, accelerator)
    if cfg.self_distill > 0:
        loss = loss + cfg.self_distill * self_distillation(outs)
    return loss, per_exit


def _task_loss(cfg: TrainConfig, selfsup, outs: list[torch.Tensor], batch: dict, accelerator: torch.device
               ) -> tuple[torch.Tensor, list[float]]:
    if selfsup is None:
        return multi_exit_loss(outs, batch["depth"].to(accelerator), cfg.exit_weights)
    keys = ("image", "sources", "K", "pose", "pose_known", "scan", "hint")
    on_accelerator = {k: torch.as_tensor(batch[k]).to(accelerator) for k in keys if k in batch}
    loss, per_exit = selfsup(outs, on_accelerator, batch_row(batch), cfg.exit_weights)
    if cfg.supervision == "mixed" and bool((batch["depth"] > 0).any()):
        dense, dense_exit = multi_exit_loss(outs, batch["depth"].to(accelerator), cfg.exit_weights)
        loss, per_exit = loss + dense, [a + b for a, b in zip(per_exit, dense_exit)]
    return loss, per_exit


def check_spec_for(cfg: TrainConfig, spec: str) -> None:
    """What ``check_data_for`` can tell from the data spec alone, before any frame is read or generated."""
    if cfg.supervision != "supervised" and not parse_data_spec(spec).is_sequence:
        raise UserError(f"--supervision {cfg.supervision} needs sequence data (synthetic-seq, "
                        f"kitti-seq:DRIVE or frames:FOLDER), not single frames ({spec})")


def check_data_for(cfg: TrainConfig, dataset) -> None:
    """Self-supervision needs sequences, and ``poses="given"`` needs sequences with poses."""
    if cfg.supervision == "supervised":
        return
    if not getattr(dataset, "sequence", False):
        raise UserError(f"--supervision {cfg.supervision} needs sequence data (synthetic-seq, "
                        "kitti-seq:DRIVE or frames:FOLDER), not single frames")
    if cfg.poses == "given" and len(dataset) and not dataset[0]["pose_known"]:
        raise UserError("--poses given: this data has no poses (KITTI needs oxts/ and calib_imu_to_velo.txt, "
                        "a folder poses.txt); use --poses net")


def image_batch(batch: dict, accelerator: torch.device | None) -> torch.Tensor:
    """The batch's images on ``accelerator`` in channels-last order: convolutions (oneDNN on CPUs, cuDNN
    on GPUs) run faster so, with the same values (bench_layout measures both)."""
    return batch["image"].to(accelerator).contiguous(memory_format=torch.channels_last)


def batch_row(batch: dict) -> "int | torch.Tensor":
    """The row the batch's scans lie on: one int where every column of every frame is on one row (the
    paper's level mount), else each frame's row per column, (N, W) (a tilted or offset LiDAR's line)."""
    rows = batch.get("scan_rows")
    if rows is not None:
        rows = torch.as_tensor(rows)
        if rows.dim() == 2 and bool((rows != rows.reshape(-1)[0]).any()):
            return rows
    return int(torch.as_tensor(batch["scan_row"]).float().median().item())


def evaluate(net: AnytimeDepthNet, dataset, batch_size: int = 8, accelerator: torch.device | None = None,
             limit: int | None = None, median_scaling: bool = False) -> pd.DataFrame:
    """Per-path metrics (averaged per image, FastDepth's convention): one row per path, computed on
    ``accelerator`` (default: where the network's weights are). ``dataset`` is a data set, or a list
    of ready batches (dicts of batched tensors); ``limit``: stop after the batch that reaches this many
    frames.

    On sequence data, MonoDepth2's conventions: predictions clamped to [1e-3, cap] and ground truth
    beyond the data's cap (10 m synthetic, 80 m KITTI) ignored (the Garg crop is already in KITTI
    sequences' ground truth). ``median_scaling`` (for a depth known only up to scale) multiplies
    each network path by median(ground truth) / median(prediction) per image; path 0, the scan
    itself, is metric and is never scaled. Where a sequence's frames have known poses (given, or
    measured by the LiDAR), each path also gets its :func:`photometric_score` (unscaled), the only
    score of frames without depth."""
    if isinstance(dataset, list):
        batches = dataset
    else:
        batches = DataLoader(dataset, batch_size=batch_size, shuffle=False)
    accelerator = accelerator or next(net.parameters()).device
    cap = getattr(dataset, "max_depth", None) if getattr(dataset, "sequence", False) else None
    net.eval()
    averagers = [MetricAverager() for _ in range(net.candidate.num_paths)]
    seen = 0
    with torch.no_grad():
        for batch in batches:
            outs = net(image_batch(batch, accelerator), batch["scan"].to(accelerator), batch_row(batch))
            target = batch["depth"]
            if cap is not None:
                target = torch.where(target <= cap, target, torch.zeros_like(target))
            scored = _posed(batch)
            for p, out in enumerate(outs):
                if scored is not None:
                    _add_photometric(averagers[p], out, batch, scored, accelerator)
                out = out.float().cpu()
                if cap is None and not (p > 0 and median_scaling):
                    for m in batch_depth_metrics(out, target):
                        averagers[p].add(m)
                    continue
                for i in range(out.shape[0]):
                    pred = out[i]
                    if p > 0 and median_scaling:
                        pred = pred * _median_ratio(pred, target[i])
                    if cap is not None:
                        pred = pred.clamp(1e-3, cap)
                    averagers[p].add(depth_metrics(pred, target[i]))
            seen += target.shape[0]
            if limit and seen >= limit:
                break
    rows = [{"path": p, **a.result()} for p, a in enumerate(averagers)]
    return pd.DataFrame(rows)


def _posed(batch: dict) -> torch.Tensor | None:
    """Which frames of a sequence batch have known poses (a bool per frame), or None where it has none."""
    if "sources" not in batch or "pose_known" not in batch:
        return None
    known = torch.as_tensor(batch["pose_known"]).reshape(-1).bool()
    return known if bool(known.any()) else None


def _add_photometric(averager: MetricAverager, depth: torch.Tensor, batch: dict, known: torch.Tensor,
                     accelerator: torch.device) -> None:
    """Adds each posed frame's :func:`photometric_score` of ``depth`` to ``averager`` (NaN for the others)."""
    on = {k: batch[k].to(accelerator) for k in ("image", "sources", "K", "pose")}
    scores = photometric_score(depth.float(), on).cpu()
    for score, ok in zip(scores.tolist(), known.tolist()):
        averager.add({PHOTOMETRIC: score if ok else float("nan")})


def evaluated_frames(dataset, limit: int | None, batch_size: int = 8) -> int:
    """How many frames ``evaluate(dataset, batch_size, limit=limit)`` measures: the first ones of the set,
    up to the batch that reaches ``limit``."""
    n = len(dataset)
    return n if not limit else min(n, -(-limit // batch_size) * batch_size)


def _median_ratio(pred: torch.Tensor, target: torch.Tensor) -> float:
    valid = target > 0
    if not bool(valid.any()):
        return 1.0
    return float(target[valid].median() / pred[valid].median().clamp(min=1e-6))


@dataclass
class TrainResult:
    metrics: pd.DataFrame                     # per path, on the validation set
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    images_per_second: float = 0.0
    steps: int = 0


class Pruned(Exception):
    """Raised by a report callback to stop a hopeless training early."""


def lr_at(cfg: TrainConfig, step: int) -> float:
    frac = min(step / max(cfg.steps, 1), 1.0)
    return cfg.lr_end + (cfg.lr - cfg.lr_end) * (1 - frac) ** 0.9


def save_checkpoint(path: Path, net: AnytimeDepthNet, cfg: TrainConfig, step: int,
                    optimizer: torch.optim.Optimizer | None = None, extra: dict | None = None) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"candidate": net.candidate.to_dict(), "state_dict": net.state_dict(), "train_config": cfg.to_dict(),
             "step": step, "optimizer": optimizer.state_dict() if optimizer else None, **(extra or {})}
    remove_dead_scratch(path.parent, only_for=path)   # what a save of this checkpoint killed midway left
    with writing_atomically(path) as f:   # never a half-written checkpoint, nor its scratch on a full disk
        torch.save(state, f)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    p = Path(path)
    if p.is_dir():
        raise UserError(f"checkpoint {p}: is a folder; give the .pt file explorer train wrote")
    if not p.is_file():
        raise UserError(f"checkpoint {p}: no such file")
    try:
        state = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt or foreign files
        raise UserError(f"checkpoint {p}: not a checkpoint PyTorch can read (a damaged or foreign file, "
                        f"{type(exc).__name__}); give the .pt file explorer train wrote") from None
    if not isinstance(state, dict) or "candidate" not in state or "state_dict" not in state:
        raise UserError(f"checkpoint {p}: not an anytime-explorer checkpoint (no candidate/state_dict)")
    return state


def check_checkpoint_target(path: str | Path, candidate: Candidate) -> None:
    """Refuses (UserError) to train ``candidate`` onto ``path`` when the file there is not a checkpoint of
    the same network: training resumes from its own checkpoint and never replaces someone else's."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"--out {p}: is a folder; give a checkpoint file to write")
    if not p.exists():
        return
    state = load_checkpoint(p)        # an unreadable or foreign file is one line
    if state["candidate"] != candidate.to_dict():
        other = Candidate.from_dict(state["candidate"]).key
        raise UserError(f"--out {p} holds the checkpoint of another network ({other}, not {candidate.key}): give "
                        "another --out, or delete it first")


def network_from_checkpoint(path: str | Path) -> tuple[AnytimeDepthNet, dict]:
    state = load_checkpoint(path)
    net = build_network(Candidate.from_dict(state["candidate"], source=str(path)))
    net.load_state_dict(state["state_dict"])
    return net.eval(), state


def trained_on(state: dict, path: str | Path) -> str:
    """The data spec a checkpoint was trained on (the generated scenes for one that does not say), checked
    here: a recording or folder this machine cannot read is one line asking for ``--data``."""
    data = state.get("data") or "synthetic"
    try:
        return str(parse_data_spec(data))
    except UserError as exc:
        raise UserError(f"{path} was trained on '{data}', which cannot be read here ({exc}): give --data") from None


def load_encoder_weights(net: AnytimeDepthNet, path: str | Path) -> int:
    """Loads a MobileNet v1 state dict (a file the user has; weights only, never pickled code) into
    the image encoder, matching tensors in order by shape. Returns how many tensors were loaded."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"encoder weights {p}: no such file")
    try:
        source = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise UserError(f"encoder weights {p}: unreadable ({str(exc).splitlines()[0][:120]})") from None
    if isinstance(source, dict) and "state_dict" in source:
        source = source["state_dict"]
    if not isinstance(source, dict):
        raise UserError(f"encoder weights {p}: expected a state dict")
    src = [v for k, v in source.items() if isinstance(v, torch.Tensor) and v.dim() > 0
           and not k.endswith("num_batches_tracked")]
    target = net.stages["image_encoder"].state_dict()
    keys = [k for k in target if not k.endswith("num_batches_tracked")]
    loaded, j = {}, 0
    for k in keys:
        while j < len(src) and src[j].shape != target[k].shape:
            j += 1
        if j == len(src):
            break
        loaded[k] = src[j]
        j += 1
    if not loaded:
        raise UserError(f"encoder weights {p}: no tensor matches the encoder's shapes")
    net.stages["image_encoder"].load_state_dict(loaded, strict=False)
    return len(loaded)


def train(net: AnytimeDepthNet, train_set, val_set, cfg: TrainConfig = PROXY,
          accelerator: torch.device | None = None, checkpoint: Path | None = None,
          progress: Callable[[int, int, dict], None] | None = None,
          report: Callable[[int, pd.DataFrame], None] | None = None, val_limit: int | None = None,
          checkpoint_every: int = 200, data: str | None = None) -> TrainResult:
    """Trains every exit jointly for ``cfg.steps`` steps on ``accelerator`` (a torch device; the CPU if
    None). ``report(step, per_path_metrics)`` is called at each evaluation (``cfg.eval_every``) and may
    raise :class:`Pruned`. With ``checkpoint`` the state is saved every ``checkpoint_every`` steps and
    training resumes from it; ``data``, the spec of the data trained on, is saved with it
    (:func:`trained_on` reads it)."""
    accelerator = accelerator or torch.device("cpu")
    cfg.validate()
    torch.manual_seed(cfg.seed)
    net.to(device=accelerator, memory_format=torch.channels_last)   # see image_batch
    train_set, selfsup = _self_supervision(cfg, train_set, accelerator)
    opt = _optimizer(cfg, net, selfsup)
    use_amp = cfg.amp and accelerator.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp)
    start = _resume(checkpoint, net, selfsup, opt, accelerator)
    gen = torch.Generator().manual_seed(cfg.seed)
    # on a GPU, the data held there where it fits (explorer.data.resident: the same batches)
    loader = training_batches(train_set, cfg.batch_size, gen, accelerator) if accelerator.type == "cuda" else \
        DataLoader(train_set, batch_size=cfg.batch_size, shuffle=True, generator=gen, drop_last=True)
    if len(loader) == 0:
        loader = DataLoader(train_set, batch_size=len(train_set), shuffle=True, generator=gen)
    history: list[dict] = []
    # the pose network travels with the checkpoint so that a resumed run continues it
    extra = {"data": data, **({"selfsup": selfsup.state_dict()} if selfsup is not None else {})}
    step, seen, t0 = start, 0, time.perf_counter()
    epoch = 0
    # Ctrl-C or SIGTERM ends training at the end of a step, with the weights reached saved (resumed from)
    stop = StopAtStep(None if checkpoint is None else lambda at: save_checkpoint(checkpoint, net, cfg, at, opt, extra),
                      checkpoint, start, cfg.steps)
    with stop:
        while step < cfg.steps:
            if hasattr(train_set, "epoch"):
                train_set.epoch = epoch
            for batch in loader:
                if step >= cfg.steps:
                    break
                net.train()
                for g in opt.param_groups:
                    g["lr"] = lr_at(cfg, step)
                opt.zero_grad(set_to_none=True)
                loss, per_exit, frames = _backward(net, cfg, selfsup, batch, accelerator, scaler, step)
                scaler.step(opt)
                scaler.update()
                step += 1
                seen += frames
                record = {"step": step, "loss": float(loss.detach()), **{f"exit_{i + 1}": li for i, li in enumerate(per_exit)}}
                history.append(record)
                if progress:
                    progress(step, cfg.steps, record)
                if checkpoint is not None and step % checkpoint_every == 0:
                    save_checkpoint(checkpoint, net, cfg, step, opt, extra)
                if report and cfg.eval_every and step % cfg.eval_every == 0 and step < cfg.steps:
                    report(step, evaluate(net, val_set, accelerator=accelerator, limit=val_limit,
                                          median_scaling=not cfg.metric))
                stop.check(step)   # a Ctrl-C during the step: its weights saved, then stopped
            epoch += 1
    seconds = time.perf_counter() - t0
    metrics = evaluate(net, val_set, accelerator=accelerator, limit=val_limit, median_scaling=not cfg.metric)
    if checkpoint is not None:
        save_checkpoint(checkpoint, net, cfg, step, opt, extra)
    net.to(memory_format=torch.contiguous_format)  # hand back an ordinary module (export, runtime)
    return TrainResult(metrics, history, seconds, seen / seconds if seconds > 0 else 0.0, step)


def _backward(net: AnytimeDepthNet, cfg: TrainConfig, selfsup, batch: dict, accelerator: torch.device,
              scaler: torch.amp.GradScaler, step: int) -> tuple[torch.Tensor, list[float], int]:
    """One step's forward and backward passes: over the whole batch, or over ``cfg.micro_batches``
    parts of it one after another (the same mean gradient, each part's activations alone in memory,
    BatchNorm's statistics per part); (loss, per-exit losses, frames), averaged over the parts."""
    row, use_amp = batch_row(batch), scaler.is_enabled()
    frames = len(batch["image"])
    parts = min(max(cfg.micro_batches, 1), frames)
    loss_sum, exits_sum = None, None
    for i in range(parts):
        part = batch if parts == 1 else _part(batch, slice(i * frames // parts, (i + 1) * frames // parts), frames)
        with torch.autocast(accelerator.type, dtype=torch.float16, enabled=use_amp):
            outs = net(image_batch(part, accelerator), part["scan"].to(accelerator), row)
            loss, per_exit = _training_loss(cfg, selfsup, outs, part, accelerator)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training loss became {float(loss.detach())} at step {step}")
        scaler.scale(loss / parts).backward()
        loss_sum = loss.detach() / parts + (0 if loss_sum is None else loss_sum)
        exits_sum = [e / parts + (0 if exits_sum is None else exits_sum[j]) for j, e in enumerate(per_exit)]
    return loss_sum, exits_sum, frames


def _part(batch: dict, rows: slice, frames: int) -> dict:
    """The frames ``rows`` of a collated batch (entries that are not per frame are kept whole)."""
    return {k: v[rows] if not isinstance(v, str) and hasattr(v, "__len__") and len(v) == frames else v
            for k, v in batch.items()}


def _self_supervision(cfg: TrainConfig, train_set, accelerator: torch.device):
    """(training set, self-supervised loss module or None): with depth hints, the set is wrapped to
    carry each frame's hint (computed once per data set, cached)."""
    if cfg.supervision == "supervised":
        return train_set, None
    check_data_for(cfg, train_set)
    if cfg.hints:
        if not isinstance(train_set, HintedDataset):
            train_set = with_hints(train_set)
    return train_set, SelfSupervisedLoss(cfg.poses, cfg.scan_loss).to(accelerator)


def adamw(params, lr: float, weight_decay: float) -> torch.optim.AdamW:
    """AdamW, fused where PyTorch has a fused kernel for the parameters' device (CPU, CUDA): one pass
    over all tensors instead of several small operations per tensor, which on a GPU are as many kernel
    launches (bench_optimizer)."""
    params = list(params)
    fused = all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
    return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, fused=fused or None)


def _optimizer(cfg: TrainConfig, net: AnytimeDepthNet, selfsup) -> torch.optim.Optimizer:
    """One optimizer over the network and, with self-supervision, the pose network."""
    params = [p for p in net.parameters() if p.requires_grad]
    if selfsup is not None:
        params += [p for p in selfsup.parameters() if p.requires_grad]
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return adamw(params, cfg.lr, cfg.weight_decay)
    raise UserError(f"unknown optimizer '{cfg.optimizer}': use sgd or adamw")


def _resume(checkpoint: Path | None, net: AnytimeDepthNet, selfsup, opt: torch.optim.Optimizer,
            accelerator: torch.device) -> int:
    """The step to start from: the checkpoint's, with its weights and optimizer state loaded, when it
    holds this candidate and an optimizer state (a weights-only file starts over); else 0."""
    if checkpoint is None or not Path(checkpoint).is_file():
        return 0
    state = load_checkpoint(checkpoint, accelerator)
    if state["candidate"] != net.candidate.to_dict() or not state.get("optimizer"):
        return 0
    net.load_state_dict(state["state_dict"])
    if selfsup is not None and state.get("selfsup"):
        selfsup.load_state_dict(state["selfsup"])
    opt.load_state_dict(state["optimizer"])
    return int(state["step"])
