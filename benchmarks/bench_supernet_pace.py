"""How well a time limit's plan knows what its supernet will take: the seconds a step as the plan
measures it (``explorer.supernet.pace.seconds_per_step``: a few steps of each phase of the recipe,
weighted by their share), as a short run of the recipe reads it (its first 6 steps, the median after
the first two: mostly the second phase, where progressive shrinking no longer keeps every width full),
and as the whole recipe takes it (its wall time over its steps, data loading aside).

    python benchmarks/bench_supernet_pace.py [--reps 3] [--steps 300] [--threads 2]

Each repetition runs the two measurements and the whole recipe one after the other, their order turning
from one repetition to the next, on the default space and data (generated before anything is timed).
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import Bench, interleave  # noqa: E402

from explorer.data import open_dataset  # noqa: E402
from explorer.space import SearchSpace  # noqa: E402
from explorer.study.config import SearchConfig  # noqa: E402
from explorer.supernet import read_supernet, train_supernet  # noqa: E402
from explorer.supernet.pace import seconds_per_step  # noqa: E402

SHORT_RUN_STEPS = 6


def short_run(space: SearchSpace, data: str, recipe, folder: Path) -> float:
    """The median step of a 6-step run of ``recipe`` after its first two (the step times from the progress
    marks, as they come one step late)."""
    marks: dict[int, float] = {}
    train_supernet(space, data, dataclasses.replace(recipe, steps=SHORT_RUN_STEPS), folder / "short.pt",
                   torch.device("cpu"), progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()))
    (folder / "short.pt").unlink()
    steps = sorted(marks)
    return statistics.median(marks[b] - marks[a] for a, b in zip(steps, steps[1:]) if a >= 2)


def whole_recipe(space: SearchSpace, data: str, recipe, folder: Path) -> float:
    """The seconds a step of the whole ``recipe``, as its file records its training time."""
    out = train_supernet(space, data, recipe, folder / "whole.pt", torch.device("cpu"))
    state = read_supernet(out)
    out.unlink()
    return float(state["seconds"]) / int(state["step"])


def main() -> None:
    bench = Bench(__file__, "the supernet's step time: the plan's measurement against the whole recipe", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=300, help="the whole recipe's steps (default 300)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = bench.parse_args(ap)
    torch.set_num_threads(args.threads)
    space, config = SearchSpace.from_yaml("anytime_depth"), SearchConfig(study="supernet-pace")
    recipe = dataclasses.replace(config.supernet_recipe(), steps=args.steps)
    open_dataset(config.data, "train", recipe.input_size, seed=recipe.seed)
    bench.figure("whole_step_s", f"the whole recipe ({args.steps} steps): seconds a step", "s")
    bench.figure("phases_step_s", "the plan's measurement (both phases, weighted): seconds a step", "s")
    bench.figure("short_run_step_s", f"a {SHORT_RUN_STEPS}-step run's median step", "s")
    bench.figure("phases_ratio", "the plan's measurement / the whole recipe's", "")
    bench.figure("short_run_ratio", f"the {SHORT_RUN_STEPS}-step run's / the whole recipe's", "")
    with tempfile.TemporaryDirectory(prefix="bench-supernet-pace-") as tmp:
        for rep in bench.repetitions():
            got = interleave({"phases": lambda: seconds_per_step(space, config.data, recipe, torch.device("cpu")),
                              "short_run": lambda: short_run(space, config.data, recipe, Path(tmp)),
                              "whole": lambda: whole_recipe(space, config.data, recipe, Path(tmp))}, rep)
            for name, value in got.items():
                bench.add(f"{name}_step_s", value)
            for name in ("phases", "short_run"):
                bench.add(f"{name}_ratio", got[name] / got["whole"])
    bench.note(f"cpu, torch threads {args.threads}; the default space, data and supernet recipe with {args.steps} "
               "steps")
    bench.finish()


if __name__ == "__main__":
    main()
