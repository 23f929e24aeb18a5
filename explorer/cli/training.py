"""``explorer train``, ``evaluate`` and ``supernet``: training one candidate, or the space's supernet."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from explorer.errors import UserError, kept_if_refused
from explorer.files import check_writable_folder
from explorer.space import check_size
from explorer.cli.inspect import _candidates_of
from explorer.cli._common import (HEAD_KINDS, _add_supervision, _Parser, _size, deprecated_alias, smallest_status,
                                  train_on_free_cores)


def cmd_train(args) -> None:
    import dataclasses
    from explorer.console import console, print_frame, progress
    from explorer.data import open_dataset
    from explorer.model import build_network
    from explorer.training.train import (RECIPES, check_checkpoint_target, check_data_for, check_spec_for,
                                         load_encoder_weights, resolve_accelerator, train)
    candidate = _candidates_of(args.candidate)
    if len(candidate) != 1:
        raise UserError(f"{args.candidate} holds {len(candidate)} candidates: train takes one")
    candidate = candidate[0]
    cfg = RECIPES[args.recipe]
    changes = {k: v for k, v in (("steps", args.steps), ("batch_size", args.batch_size),
                                 ("input_size", args.train_size), ("lr", args.lr), ("seed", args.seed))
               if v is not None}
    cfg = dataclasses.replace(cfg, **changes, supervision=args.supervision, poses=args.poses,
                              scan_loss=not args.no_scan_loss, hints=args.depth_hints, self_distill=args.self_distill,
                              exit_weights=_exit_weights(args.exit_weights, candidate, args.device, args.budget))
    cfg.validate()
    check_size(cfg.input_size, candidate.working_stride, "--train-size")
    if candidate.downscale > 1:   # it works at --train-size: its frames are that much larger (and recorded so)
        cfg = dataclasses.replace(cfg, input_size=candidate.frame_size(cfg.input_size))
        console.print(f"frames at {cfg.input_size[0]}x{cfg.input_size[1]}: the network works at 1/{candidate.downscale} "
                      "of its input size")
    check_spec_for(cfg, args.data)
    out = Path(args.out or f"reports/checkpoints/{candidate.key}.pt")
    check_checkpoint_target(out, candidate)
    check_writable_folder(out.parent, "checkpoint", "give --out a file in a folder you can write", keep=False)
    if cfg.exit_weights:
        console.print("exit loss weights: " + " ".join(f"{w:.3f}" for w in cfg.exit_weights))
    accelerator = resolve_accelerator(args.accelerator)
    train_on_free_cores()
    with progress(transient=True) as bar:
        task = bar.add_task("generating synthetic scenes (once, then cached)", total=None, status="")
        train_set = open_dataset(args.data, "train", cfg.input_size, seed=cfg.seed,
                                 progress=lambda i, n: bar.update(task, completed=i, total=n))
    val_set = open_dataset(args.data, "val", cfg.input_size, train_augment=False)
    check_data_for(cfg, train_set)
    if cfg.hints:
        from explorer.training.depth_hints import with_hints
        with progress(transient=True) as bar:
            task = bar.add_task("depth hints (once per data set, then cached)", total=len(train_set), status="")
            train_set = with_hints(train_set, progress=lambda i, n: bar.update(task, completed=i))
    import torch
    torch.manual_seed(cfg.seed)
    net = build_network(candidate)
    if args.encoder_weights:
        n = load_encoder_weights(net, args.encoder_weights)
        console.print(f"loaded {n} encoder tensors from {args.encoder_weights}")
    with progress() as bar, kept_if_refused(_kept(out, "checkpoint")):
        task = bar.add_task(f"training ({cfg.supervision})", total=cfg.steps, status="")
        result = train(net, train_set, val_set, cfg, accelerator, checkpoint=out, data=args.data,
                       progress=lambda s, n, r: bar.update(task, completed=s, status=f"loss {r['loss']:.3f}"))
    console.print(f"saved {out} ({result.steps} steps, {result.images_per_second:.1f} images/s)")
    if result.metrics is not None and result.metrics.drop(columns="path", errors="ignore").isna().all().all():
        console.print(f"no validation metrics: the validation frames of {args.data} have no depth to measure on")
        return
    print_frame(result.metrics, "validation, per path" + ("" if cfg.metric else " (median-scaled: no scan term)"))


def _kept(out: Path, what: str):
    """What a training whose save the disk refused kept, for its one line (``kept_if_refused``)."""
    return lambda: (f"{out} keeps the last {what} saved, and the same command resumes from it" if out.is_file()
                    else f"no {what} was saved yet: run the same command again")


def _exit_weights(spec: str, candidate, profile: str, budget: str) -> tuple[float, ...] | None:
    exits = candidate.num_paths - 1
    if spec == "equal":
        return None
    if spec == "anytime":
        from explorer.anytime import exit_loss_weights, parse_budget
        from explorer.cost import candidate_cost, get_device
        dist = parse_budget(budget)
        return exit_loss_weights(candidate_cost(candidate).path_costs(get_device(profile), dist.kind), dist)
    try:
        weights = tuple(float(w) for w in spec.split(","))
    except ValueError:
        raise UserError(f"--exit-weights {spec}: use equal, anytime or one number per exit (W1,W2,...)") from None
    if len(weights) != exits or min(weights) < 0 or sum(weights) <= 0:
        raise UserError(f"--exit-weights {spec}: give {exits} non-negative numbers, one per exit of "
                        f"{candidate.key}, not all 0")
    return weights


def cmd_evaluate(args) -> None:
    from explorer.console import print_frame, print_json
    from explorer.data import open_dataset
    from explorer.training.train import TrainConfig, evaluate, network_from_checkpoint, trained_on
    net, state = network_from_checkpoint(args.checkpoint)
    data = args.data or trained_on(state, args.checkpoint)
    recipe = TrainConfig.from_dict(state["train_config"])
    size = check_size(args.input_size or recipe.input_size, net.stride, "--input-size")
    ds = open_dataset(data, args.split, size, train_augment=False)
    # a depth known only up to scale (self-supervised without the scan term) is median-scaled
    frame = evaluate(net, ds, limit=args.frames, median_scaling=not recipe.metric)
    if args.json:
        print_json({"checkpoint": args.checkpoint, "data": str(ds.name), "input_size": list(size),
                    "supervision": recipe.supervision, "median_scaling": not recipe.metric,
                    "paths": frame.to_dict("records")})
    else:
        print_frame(frame[["path", "rmse", "mae", "rel", "delta1", "delta2", "delta3"]],
                    f"{args.checkpoint} on {ds.name} ({args.split}) at {size[0]}x{size[1]}")


def cmd_supernet_train(args) -> None:
    from explorer.console import console, progress
    from explorer.space import SearchSpace
    from explorer.supernet import default_path, train_supernet
    from explorer.supernet.train import read
    from explorer.training.train import resolve_accelerator
    space = SearchSpace.from_yaml(args.space)   # the numbers were checked by check_numbers (AT_LEAST)
    recipe = supernet_recipe(args)
    out = Path(args.out) if args.out else default_path(space, args.data, recipe)
    check_writable_folder(out.parent, "supernet", "give --out a file in a folder you can write", keep=False)
    train_on_free_cores()
    with progress() as bar, kept_if_refused(_kept(out, "supernet")):
        task = bar.add_task("supernet", total=recipe.steps, status="")
        data = bar.add_task("data", total=None, status="", visible=False)
        path = train_supernet(
            space, args.data, recipe, out, resolve_accelerator(args.accelerator),
            progress=lambda s, n, r: bar.update(task, completed=s, status=_supernet_status(r)),
            data_progress=lambda i, n: bar.update(data, completed=i, total=n, visible=True,
                                                  description="generating synthetic scenes (once)"),
            checkpoint_every=max(args.checkpoint_every, 1), stop_after_steps=args.stop_after_steps)
    if int(os.environ.get("RANK", "0")) != 0:   # under torchrun, the first process speaks for all
        return
    state = read(path)
    console.print(f"supernet of {space.name}: {path} (step {state['step']}/{recipe.steps}, "
                  f"{state['seconds'] / 60:.1f} min of training)")


def supernet_recipe(args):
    """The ``--recipe`` named, with the options given on the command line in its place."""
    import dataclasses
    from explorer.supernet.train import RECIPES
    changes = {k: v for k, v in (("steps", args.steps), ("batch_size", args.batch_size),
                                 ("input_size", args.train_size), ("lr", args.lr), ("amp", args.amp),
                                 ("shrink", args.shrink)) if v is not None}
    if args.lr is not None:
        changes["lr_end"] = args.lr / 10
    return dataclasses.replace(RECIPES[args.recipe], **changes, random_subnets=args.random_subnets,
                               micro_batches=args.micro_batches, seed=args.seed, teacher_depths=args.teacher_depths,
                               head_kinds=args.head_kinds, distill=args.distill, cuda_graphs=args.cuda_graphs,
                               self_distill=args.self_distill)


def _supernet_status(record: dict) -> str:
    """The losses, the last step's time and, on CUDA, the most GPU memory held so far."""
    text = (f"largest {record['largest']:.3f}, {smallest_status(record)}, random {record['random']:.3f}, "
            f"{record['step_seconds']:.3f} s/step")
    if "gpu_memory_mb" in record:
        text += f", GPU {record['gpu_memory_mb']:.0f} MiB"
    return text


def cmd_supernet_show(args) -> None:
    from explorer.console import console, print_json
    from explorer.supernet.train import read
    state = read(args.file)
    info = {k: state[k] for k in ("space_name", "space_key", "data", "recipe", "step", "complete", "seconds")}
    info["last"] = state["history"][-1] if state.get("history") else None
    if args.json:
        print_json(info)
        return
    console.print(f"{args.file}: space {info['space_name']} ({info['space_key']}), data {info['data']}, "
                  f"step {info['step']}/{info['recipe']['steps']}{' (complete)' if info['complete'] else ''}, "
                  f"{info['seconds'] / 60:.1f} min")
    console.print(f"  recipe: {info['recipe']}")


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    s = add("train", cmd_train, "train a candidate (all exits) and save a checkpoint")
    s.add_argument("candidate", help="candidate YAML or one-point space (e.g. paper)")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--lidar")
    s.add_argument("--recipe", default="proxy", choices=["proxy", "paper"])
    s.add_argument("--steps", type=int)
    s.add_argument("--batch-size", type=int)
    s.add_argument("--train-size", type=_size, help="training resolution HxW (default: the recipe's)")
    deprecated_alias(s, "--input-size", "--train-size")
    deprecated_alias(s, "--input", "--train-size")
    s.add_argument("--lr", type=float)
    s.add_argument("--seed", type=int)
    s.add_argument("--encoder-weights", help="MobileNet v1 state dict file to start the encoder from")
    s.add_argument("--exit-weights", default="equal", metavar="equal|anytime|W1,W2,...",
                   help="weights of the exits' losses: equal (default), anytime (each exit's share of the "
                   "anytime loss for --device and --budget, mixed 3:1 with equal weights so that every exit "
                   "learns), or one number per exit")
    s.add_argument("--device", default="tx2", help="device profile for --exit-weights anytime (default tx2)")
    s.add_argument("--budget", default="time:uniform:33ms",
                   help="budget distribution for --exit-weights anytime (default time:uniform:33ms)")
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--out", help="checkpoint file to write (default reports/checkpoints/KEY.pt); training "
                   "resumes from it if it exists")
    _add_supervision(s)
    s.add_argument("--no-scan-loss", action="store_true",
                   help="self-supervision without the L1 term on the scan row: depth only up to scale, "
                   "evaluated with median scaling")

    s = add("evaluate", cmd_evaluate, "per-path metrics of a checkpoint on a data set")
    s.add_argument("checkpoint")
    s.add_argument("--data", help="data set to measure on (default: the data the checkpoint was trained on)")
    s.add_argument("--lidar")
    s.add_argument("--split", default="val", choices=["train", "val"])
    s.add_argument("--input-size", type=_size, help="evaluation resolution HxW (default: the training size)")
    deprecated_alias(s, "--input", "--input-size")
    s.add_argument("--frames", type=int)
    deprecated_alias(s, "--limit", "--frames")
    s.add_argument("--json", action="store_true")

    _register_supernet(add("supernet", None, "train or inspect the weight-sharing supernet of a space"))


def _register_supernet(sp) -> None:
    nsub = sp.add_subparsers(dest="sub", required=True, parser_class=_Parser, metavar="SUBCOMMAND")
    s = nsub.add_parser("train", help="train (or resume) a supernet: the sandwich rule",
                        description="Train the supernet of a space once; every study on that space, data and "
                        "recipe reuses it. Resumes after a kill. Data parallel under torchrun "
                        "(torchrun --nproc_per_node N -m explorer supernet train ...).")
    s.add_argument("--space", default="anytime_depth")
    s.add_argument("--data", default="synthetic")
    s.add_argument("--lidar")
    s.add_argument("--recipe", default="default", choices=["default", "gpu"],
                   help="default: 64x64, batches of 16, float32 (what a search trains on a CPU); gpu: 224x224, "
                   "batches of 64, bf16 autocast (keeps a GPU busy). --steps, --train-size, --batch-size, --lr "
                   "and --amp override the recipe's")
    s.add_argument("--steps", type=int, help="training steps (default 600, what a search uses)")
    s.add_argument("--train-size", type=_size, help="training resolution HxW (default: the recipe's)")
    deprecated_alias(s, "--input-size", "--train-size")
    deprecated_alias(s, "--input", "--train-size")
    s.add_argument("--batch-size", type=int, help="global batch over all processes (default: the recipe's)")
    s.add_argument("--lr", type=float, help="peak learning rate, decaying to a tenth (default 2e-3)")
    s.add_argument("--amp", action=argparse.BooleanOptionalAction, default=None,
                   help="bf16 autocast of the forward passes (default: the recipe's; on a CPU it is slower)")
    s.add_argument("--random-subnets", type=int, default=1, help="random subnets per step besides the largest "
                   "and the smallest (default 1)")
    s.add_argument("--teacher-depths", choices=["cycle", "max"], default="cycle",
                   help="encoder depth of the largest subnet (the one distilled from, with --distill): cycle (default) "
                   "turns over the space's depths step by step, so shallow encoders are not ranked below deep "
                   "ones for lack of training; max always takes the deepest (the plain sandwich rule)")
    s.add_argument("--head-kinds", choices=HEAD_KINDS, default="rotate", help="which subnet trains which kind "
                   "of exit head (depth x residual): rotate (default) hands the kinds in turn to every subnet of a "
                   "step, so each kind trains on the largest, the smallest and random backbones; cover gives the "
                   "random subnets the kinds the largest and smallest do not train; random lets them draw one")
    s.add_argument("--shrink", type=float, metavar="F", help="progressive shrinking: this fraction of the steps "
                   "trains full-width subnets only (depths, exits and heads still vary) before every width trains "
                   "(default: the recipe's, 0.5; 0: every width from the start)")
    s.add_argument("--distill", type=float, default=0.0, metavar="W", help="weight, in the other subnets' "
                   "loss, of the largest subnet's last exit (in-place distillation; default 0: off, the supernet "
                   "ranked stand-alone results better without it)")
    s.add_argument("--self-distill", type=float, default=0.0, metavar="W", help="weight of self-distillation: "
                   "every subnet's exits before its last also learn its last exit's map, detached (default 0: off)")
    s.add_argument("--micro-batches", type=int, default=1, help="split each process's batch (gradient "
                   "accumulation; BatchNorm statistics per micro-batch)")
    s.add_argument("--cuda-graphs", action=argparse.BooleanOptionalAction, default=True,
                   help="on a GPU, replay each stage from a CUDA graph, captured the first time a subnet has it "
                   "(default: on; the same updates, launched at once instead of kernel by kernel)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--accelerator", default="auto", choices=["auto", "cpu", "cuda"])
    s.add_argument("--out", help="supernet file to write (default: a file in the cache, where searches find it); "
                   "training resumes from it if it exists")
    s.add_argument("--checkpoint-every", type=int, default=100, help="steps between checkpoints (default 100)")
    s.add_argument("--stop-after-steps", type=int, metavar="N", help="stop this run after N more steps, short of "
                   "--steps, with the file saved to resume from (default: train to --steps)")
    deprecated_alias(s, "--max-steps", "--stop-after-steps")
    s.set_defaults(fn=cmd_supernet_train)
    s = nsub.add_parser("show", help="what a supernet file holds: space, data, recipe, progress")
    s.add_argument("file")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_supernet_show)
