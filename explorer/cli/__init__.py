"""The ``explorer`` command line, one module per command group. Every mistake a user can make is one
line on stderr, exit 2. SIGTERM ends a command as Ctrl-C does: what it was writing, and its scratch
folders, are cleaned up on the way out."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import warnings
from typing import Sequence

from explorer.cli import deploy, devices, inspect, notebook, study, training
from explorer.cli._common import RUNTIME, _Parser, check_numbers, explain, resolve_data, runtime_install
from explorer.cli.study import _print_outcome  # noqa: F401  (the closing summary, for tests and notebooks)
from explorer.errors import UserError, refused_line, refused_write
from explorer.files import remove_own_scratch, sigterm_unwinds

GROUPS = (inspect, devices, training, study, deploy, notebook)


def build_parser() -> argparse.ArgumentParser:
    """The whole ``explorer`` parser, every command and option with its help, without parsing anything
    (``main`` parses with it; the documentation's CLI reference is generated from it)."""
    from explorer import __version__
    p = _Parser(prog="explorer", description="Hardware-aware design-space explorer for anytime depth estimation "
                "(camera + 2D LiDAR): search early-exit networks for the lowest anytime loss on a device.")
    p.add_argument("--version", action="version", version=f"anytime-explorer {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")

    def add(name, fn, help_):
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(fn=fn)
        return sp

    reports = dict(default="reports", help="where studies live (default: reports/)")

    for group in GROUPS:
        group.register(sub, add, reports)
    explain(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    warnings.filterwarnings("ignore", category=UserWarning, module="torch")
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "devices" and args.action == "show" and not args.name:
        parser.error("devices show needs a NAME")
    if args.command == "devices" and args.name and not args.action:
        args.name, args.action = args.name, "show"
    try:
        with sigterm_unwinds():
            check_numbers(args)
            resolve_data(args)
            args.fn(args)
    except UserError as exc:
        sys.stderr.write(f"explorer: error: {exc}\n")
        return 2
    except SystemExit as exc:
        if exc.code == 128 + signal.SIGTERM:   # what its with blocks could not remove goes too
            remove_own_scratch()
        raise
    except KeyboardInterrupt as exc:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C cannot cut this line short
        sys.stderr.write(f"explorer: interrupted; {_kept(exc)}\n")
        return 130
    except ModuleNotFoundError as exc:
        if not runtime_install():
            raise
        missing = exc.name or "torch"
        missing = missing if missing.startswith("explorer.") else missing.split(".")[0]
        sys.stderr.write(f"explorer: error: explorer {args.command} is not in the runtime install ({RUNTIME}, which "
                         f"runs exported models with explorer run and has no {missing}); `pip install "
                         "anytime-explorer` has every command\n")
        return 2
    except Exception as exc:   # a full disk, a folder made read-only meanwhile: one line, what was kept
        refused = refused_write(exc)
        if refused is None:
            raise
        sys.stderr.write(f"explorer: error: {refused_line(refused)}\n")
        return 2
    return 0


def _kept(exc: BaseException | None) -> str:
    """What an interrupted command kept, as the command said it (a search, a training run), or as a
    second Ctrl-C's interrupt carries it from the first one's."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt) and exc.args:
            return str(exc.args[0])
        exc = exc.__context__
    return "finished trials and checkpoints are kept"


if __name__ == "__main__":
    sys.exit(main())
