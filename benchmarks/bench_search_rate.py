"""A supernet search as ``explorer search --device tx2`` runs it on this machine: distinct candidates
evaluated per minute, and the share of the sampling time spent in the evaluator (the rest is the
sampler, costing and the study's storage). The default data and the default supernet (600 steps,
cached; trained first, untimed, where it is missing), on the device a search picks (CUDA where PyTorch
sees a GPU, else the CPU).

    python benchmarks/bench_search_rate.py [--reps 3] [--seconds 60] [--device cpu|cuda]

Each repetition samples ``--seconds`` on a fresh study; an untimed search first builds what a long
search has built by then (the costing's stage cache, cuDNN's plans on a GPU). Sampling time runs from
the first trial's start to the last one's end.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import search_config, search_rate  # noqa: E402
from harness import Bench  # noqa: E402


def main() -> None:
    bench = Bench(__file__, "a supernet search's throughput: distinct candidates per minute, evaluator share",
                  __doc__)
    ap = bench.parser()
    ap.add_argument("--seconds", type=float, default=60.0, help="sampling time per repetition (default 60)")
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"],
                    help="where the evaluator runs (default: CUDA where PyTorch sees a GPU, else the CPU)")
    ap.add_argument("--data", default="synthetic", help="data set (default: the search's, synthetic)")
    ap.add_argument("--supernet-steps", type=int, default=600, help="the supernet's steps (default 600, "
                    "the search's)")
    args = bench.parse_args(ap)
    import torch
    from explorer.study.search import ensure_supernet
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    ensure_supernet(search_config("search-rate", device, args.data, args.supernet_steps).resolve())   # not timed
    rate = bench.figure("candidates_per_minute", "distinct candidates per minute", "1/min", "higher")
    per_ten = bench.figure("candidates_per_10_min", "distinct candidates per 10 minutes", "", "higher")
    share = bench.figure("evaluator_share", "share of sampling time in the evaluator", "", "higher")
    bench.note(f"{device}, {torch.get_num_threads()} threads; data {args.data}; {args.supernet_steps}-step "
               f"supernet; {args.seconds:g} s of sampling a repetition, after an untimed one")
    search_rate(device, args.data, args.seconds, args.supernet_steps)   # warm-up, untimed
    for _ in bench.repetitions():
        per_minute, in_evaluator = search_rate(device, args.data, args.seconds, args.supernet_steps)
        bench.add(rate, per_minute)
        bench.add(per_ten, per_minute * 10)
        bench.add(share, in_evaluator)
    bench.finish()


if __name__ == "__main__":
    main()
