"""What every command group shares: the one-line-error parser, argument types, the flags' common
explanations and the one way an old flag name is kept working (``deprecated_alias``)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from explorer.errors import UserError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + line)
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(2)

    def _get_value(self, action, arg_string):
        """A number is written in ASCII: Python's int() and float() also read other scripts' digits
        ('٣' as 3), which no other tool reading the same command line or study would."""
        numeric = action.type in (int, float) or getattr(action.type, "ascii_digits", False)
        if numeric and isinstance(arg_string, str) and not arg_string.isascii():
            name = max(action.option_strings, key=len) if action.option_strings else action.dest
            raise argparse.ArgumentError(None, f"{name} {arg_string!r}: write numbers with the digits 0-9")
        return super()._get_value(action, arg_string)


def ascii_digits(parse):
    """Marks an argparse type as a number's: :class:`_Parser` refuses non-ASCII text for it."""
    parse.ascii_digits = True
    return parse


class _DeprecatedAlias(argparse.Action):
    """An old spelling of an option: stores into the new option's ``dest`` and says, in one line on
    stderr, which name to use instead (stdout stays clean for --json)."""

    def __init__(self, option_strings, dest, new: str, **kwargs) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        sys.stderr.write(f"explorer: {self.option_strings[0]} is deprecated, use {self.new} "
                         "(the old name goes in the next version)\n")
        setattr(namespace, self.dest, values)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str) -> None:
    """Keeps ``old`` working for one version as another name of the already added option ``new``:
    same value type, same destination, hidden from --help (the help and the docs say ``new`` only)."""
    target = next(a for a in parser._actions if new in a.option_strings)
    parser.add_argument(old, action=_DeprecatedAlias, new=new, dest=target.dest, type=target.type,
                        metavar=target.metavar, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


#: the supernet recipe's head_kinds (explorer.supernet's HEAD_KINDS, named here so that --help needs no torch)
HEAD_KINDS = ("rotate", "cover", "random")

#: The smallest value each numeric option takes (and whether it may equal it), checked for every
#: command before any work starts: a count of 0, a negative rate or an infinite time is a mistake.
AT_LEAST = {  # dest: (minimum, inclusive)
    "batch_size": (1, True), "calibration_frames": (1, True), "checkpoint_every": (1, True),
    "deadline": (0, False), "deadlines": (1, True), "eval_frames": (1, True), "finalist_steps": (1, True),
    "finalists": (0, True), "frames": (1, True), "lr": (0, False), "max_degradation": (0, True),
    "max_first_exit": (0, False), "max_params": (0, False), "max_retries": (0, True), "micro_batches": (1, True),
    "proxy_steps": (1, True), "random_subnets": (0, True), "repeats": (1, True), "steps": (1, True),
    "stop_after_steps": (1, True), "supernet_steps": (1, True), "threads": (1, True), "time_limit": (0, True),
    "timeout": (0, True), "top": (1, True), "trial": (0, True), "trials": (1, True), "workers": (1, True),
    "seed": (0, True),
}
#: The largest value some options take, and why
AT_MOST = {  # dest: (maximum, reason)
    "batch_size": (65536, "frames in one training step"),
    "seed": (2**32 - 1, "the seeds NumPy and Optuna's samplers take"),
}


def check_numbers(args: argparse.Namespace) -> None:
    """Every numeric option in ``args`` finite and at least its ``AT_LEAST`` minimum, else one line."""
    for dest, (low, inclusive) in AT_LEAST.items():
        value = getattr(args, dest, None)
        if value is None or isinstance(value, bool):
            continue
        flag = "--" + dest.replace("_", "-")
        if not math.isfinite(value):
            raise UserError(f"{flag} {value}: give a finite number")
        if value < low or (value == low and not inclusive):
            bound = f"at least {low}" if inclusive else f"more than {low}"
            raise UserError(f"{flag} {value:g}: must be {bound}")
    for dest, (high, reason) in AT_MOST.items():
        value = getattr(args, dest, None)
        if value is not None and not isinstance(value, bool) and value > high:
            raise UserError(f"--{dest.replace('_', '-')} {value}: give at most {high} ({reason})")


def train_on_free_cores() -> None:
    """PyTorch's CPU threads set to the cores other work leaves free (explorer.training.cpu), said on
    stdout when that is fewer than usual (stderr is for the one line of an error). Data preparation
    runs on the CPU whatever trains."""
    import torch

    from explorer.console import console
    from explorer.training.cpu import use_free_cores
    usual = torch.get_num_threads()
    threads, busy = use_free_cores()
    if busy is not None and threads < usual:
        console.print(f"{busy:.1f} of this machine's cores are busy with other work: PyTorch runs on "
                          f"{threads} thread(s) instead of {usual}", markup=False, highlight=False)


def write_output(path: str | Path, text: str) -> Path:
    """A command's output file (profile, CSV table), written whole: its folder made, the file swapped in
    (``explorer.files.write_atomically``); a path that cannot be written is one line."""
    from explorer.files import write_atomically
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return write_atomically(path, text)
    except OSError as exc:
        raise UserError(f"{path}: cannot write it ({exc.strerror})") from None


def _add_provider(s: argparse.ArgumentParser) -> None:
    """``--provider``, for every command that runs graphs with onnxruntime."""
    s.add_argument("--provider", default="CPUExecutionProvider")


def _check_provider(provider: str) -> None:
    """A provider this onnxruntime lacks is one line naming those it has, before any work starts."""
    from explorer.deploy.sessions import check_provider
    check_provider(provider)


@ascii_digits
def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not HxW (e.g. 224x224)") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"'{text}': sides must be positive")
    if max(h, w) > MAX_SIDE:
        raise argparse.ArgumentTypeError(f"'{text}': at most {MAX_SIDE} pixels a side (a camera frame these "
                                         "networks take; 224x224 is the paper's)")
    return h, w


#: the largest image side a size option takes: a 4K frame's width
MAX_SIDE = 4096
#: --threads: onnxruntime's pools at most this large (more than any machine's cores only oversubscribes)
MAX_THREADS = 1024
#: --workers: search processes on one machine (each holds torch and the data: about 1 GB)
MAX_WORKERS = 64


def _bounded_int(low: int, high: int, what: str):
    """An argparse type: a whole number from ``low`` to ``high`` (``what`` names the limit's reason)."""
    @ascii_digits
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"'{text}': give {low} to {high} ({what})")
        return value
    return parse


@ascii_digits
def _count(text: str) -> float:
    """2.5M, 300k, 1500000."""
    t = text.strip().lower()
    mult = {"k": 1e3, "m": 1e6, "g": 1e9}.get(t[-1:], 1.0)
    try:
        return float(t[:-1] if t[-1:] in "kmg" else t) * mult
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a count (e.g. 2.5M)") from None


@ascii_digits
def _ms(text: str) -> float:
    from explorer.anytime import parse_quantity
    try:
        return parse_quantity(text, "time")
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@ascii_digits
def _duration_s(text: str) -> float:
    t = text.strip().lower()
    units = {"s": 1, "m": 60, "h": 3600}
    try:
        return float(t[:-1]) * units[t[-1]] if t[-1:] in units else float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a duration (e.g. 10m, 90s, 1h)") from None


def _add_supervision(s: argparse.ArgumentParser) -> None:
    s.add_argument("--supervision", default="supervised", choices=["supervised", "self", "mixed"],
                   help="supervised: L1 on dense depth (default); self: photometric reprojection between "
                   "neighbouring frames plus the scan row for metric scale (needs sequence data: "
                   "synthetic-seq, kitti-seq:DRIVE, frames:FOLDER); mixed: both where labels exist")
    s.add_argument("--poses", default="net", choices=["net", "given"],
                   help="self-supervision's camera motion: a pose network trained jointly (default), or "
                   "the data's own poses (synthetic-seq, KITTI oxts, a folder's poses.txt)")
    s.add_argument("--self-distill", type=float, default=0.0, metavar="W",
                   help="weight of self-distillation: every exit before the last also learns the last exit's "
                   "map (detached), so the early paths learn from the network's own best answer (default 0: off)")
    s.add_argument("--depth-hints", action="store_true",
                   help="self-supervision with depth hints (needs --poses given): each training frame's "
                   "depth is first optimised on the photometric loss from the scan, then pulls every exit "
                   "where it explains the neighbouring frames better (computed once per data set, cached)")


#: One explanation per flag, for every command that takes it; a command's own ``help=`` wins (a flag
#: whose meaning narrows there, e.g. ``--device`` for ``train --exit-weights anytime``). argparse formats
#: help texts with %: a percent sign is written %%.
FLAG_HELP = {
    "--json": "print the result as JSON (for scripts) instead of tables",
    "--study": "study name, as explorer search named it (DEVICE-SPACE unless given --study)",
    "--storage": "Optuna storage URL (default: the journal file reports/<study>/journal.log, or the "
                 "study's reports/<study>/study.db where it has one; postgresql://... for several machines)",
    "--space": "search space: a shipped name (anytime_depth, paper, tiny) or a YAML file",
    "--data": "data set: synthetic (generated here, cached), synthetic:TRAIN:VAL, nyu:PATH (h5 folder or CSV), "
              "kitti:PATH, rosbag:BAG; sequences: synthetic-seq[:TRAIN:VAL], kitti-seq:DRIVE, frames:FOLDER, "
              "rosbag-seq:BAG; options after commas, e.g. rosbag:run.bag,scan=/scan,tolerance=0.05 or "
              "nyu:pairs.csv,val=val.csv (see the data guide)",
    "--lidar": "lidar.yaml: your 2D LiDAR and its mount (fov, resolution, range_min, range_max, noise, dropout; "
               "height, tilt, roll, ... or T_cam_lidar). Scans are simulated with it where the data has none, "
               "and it is the mount of real scans that come without one (default: the paper's ideal centre row)",
    "--device": "device profile: a built-in name (see explorer devices) or a YAML file from explorer calibrate",
    "--budget": "budget distribution, e.g. time:uniform:33ms or energy:uniform:0.5J",
    "--metric": "the per-path error the anytime loss averages: rmse (m), mae (m) or rel",
    "--input-size": "deployment (or evaluation) resolution HxW, e.g. 224x224",
    "--train-size": "training resolution HxW, e.g. 64x64",
    "--split": "which split of the data set",
    "--frames": "at most this many frames (default: all)",
    "--provider": "onnxruntime execution provider (default CPUExecutionProvider; CUDA, TensorRT, OpenVINO, "
                  "XNNPACK ones where installed)",
    "--seed": "random seed (candidates sampled, weights initialised, batches drawn)",
    "--accelerator": "where to train: auto (CUDA when PyTorch sees a GPU, else the CPU), cpu or cuda",
    "--threads": "onnxruntime intra-op threads (default: every core this process may use)",
    "--repeats": "timed runs of each graph",
    "--lr": "learning rate",
    "--batch-size": "frames per training step",
    "--steps": "training steps of what this command trains (default: the recipe's)",
    "--recipe": "training recipe: proxy (the search's short one, at 64x64) or paper (Sec. 5.1: SGD, 20,000 steps "
                "of 96 frames at 224x224)",
    "--top": "rows to print",
    "--csv": "also write the whole table to this CSV file",
    "--image": "RGB image (PNG or JPEG) at the model's input size (any size with --lidar, resized to it)",
    "--deadlines": "deadlines spread evenly over U(0, 1.25 x the last path's predicted time)",
    "--keep-every-exit": "ship every exit: by default an exit whose error is not below an earlier path's is "
                         "left out of the network that ships (its head not computed, so later paths are ready "
                         "sooner), and every trial is scored as shipped",
    "--no-pruning": "train every proxy candidate to the end (no Optuna pruning of the worst quarter)",
    "checkpoint": "checkpoint file written by explorer train",
    "file": "supernet file (explorer supernet train --out, or the cache)",
}


def _default_text(value) -> str:
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return f"{value[0]}x{value[1]}"
    return str(value)


def explain(parser: argparse.ArgumentParser) -> None:
    """Every option of ``parser`` and of its subcommands gets its help: its own, else ``FLAG_HELP``'s,
    with its default said where the text does not say it."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                explain(sub)
            continue
        if action.help == argparse.SUPPRESS or isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        name = max(action.option_strings, key=len) if action.option_strings else action.dest
        text = action.help or FLAG_HELP.get(name, "")
        default = action.default
        if (text and "default" not in text and default not in (None, False, True)
                and not isinstance(action, argparse._AppendAction)):
            text += f" (default {_default_text(default)})"
        action.help = text


def smallest_status(record: dict) -> str:
    """A supernet step's smallest-subnet loss for progress, or that no subnet is the smallest yet
    (progressive shrinking trains full widths first)."""
    return "full widths" if record["smallest"] is None else f"smallest {record['smallest']:.3f}"


def resolve_data(args: argparse.Namespace) -> None:
    """``--data`` checked and written canonically, with ``--lidar``'s model in it: once, at the edge, so
    that a study, a supernet's cache and a checkpoint are named by what the data is."""
    if not hasattr(args, "data"):   # a command without data (explorer run's --lidar is the scan's own)
        return
    lidar = getattr(args, "lidar", None)
    data = args.data
    if not isinstance(data, str) and lidar is None:
        return
    if getattr(args, "command", None) == "curve" and runtime_install():   # the one command here with --data
        raise UserError(f"--data {data}: reading a data set needs torch, which the runtime install ({RUNTIME}) "
                        "has not; without --data explorer curve measures on the validation frames the export "
                        "carries (`pip install anytime-explorer` reads any data)")
    from explorer.data import parse_data_spec, with_lidar
    if lidar is not None:
        if not isinstance(data, str):
            raise UserError("--lidar describes the scans of --data: give --data too")
        from explorer.scan import read_lidar_options
        args.data = with_lidar(data, read_lidar_options(Path(lidar)))
    else:
        args.data = str(parse_data_spec(data))


#: the distribution that holds the runtime alone (runtime/pyproject.toml): explorer run and curve, no torch
RUNTIME = "anytime-explorer-runtime"


def runtime_install() -> bool:
    """Whether this is the runtime install: the package without its search, training and study code."""
    import importlib.util
    return importlib.util.find_spec("explorer.study") is None
