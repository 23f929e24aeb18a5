"""What depth hints cost to compute: seconds per frame of
:func:`explorer.training.depth_hints.compute_hints` (its Adam steps on a batch of frames, as
``with_hints`` runs them) at each input size. Multiplied by the training frames, it is the one-off cost
before a ``--depth-hints`` training or study (cached afterwards), which decides whether hints are
affordable at a given resolution.

    python benchmarks/bench_depth_hints.py [--sizes 64,112] [--reps 3]

The sizes alternate within each repetition, in an order that rotates.
"""

import time

import torch
from torch.utils.data import DataLoader

from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.training.depth_hints import BATCH, STEPS, compute_hints

from harness import Bench, interleave


def per_frame(batch) -> float:
    t0 = time.perf_counter()
    compute_hints(batch)
    return (time.perf_counter() - t0) / BATCH


if __name__ == "__main__":
    bench = Bench(__file__, "Depth hints: compute time per frame by input size", __doc__)
    ap = bench.parser()
    ap.add_argument("--sizes", default="64,112", help="square input sizes, comma-separated")
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    sizes = [int(s) for s in args.sizes.split(",")]
    # rendered at 128x128 (bench_selfsup's data); larger sizes are upsampled, which costs the same per pixel
    source = SyntheticSequences(ensure_synthetic_sequences(SyntheticSequenceConfig(train=480, val=48, height=128,
                                                                                   width=128)), "val")
    batches = {s: next(iter(DataLoader(SequenceDataset(source, (s, s)), batch_size=BATCH))) for s in sizes}
    for s in sizes:
        bench.figure(f"s_per_frame_{s}", f"{s}x{s}", "s/frame", "lower")
    bench.note(f"{STEPS} Adam steps, batches of {BATCH}, 2 threads; 1,200 frames (synthetic-seq's default) cost "
               "1,200 x the per-frame time, once")
    for rep in bench.repetitions():
        got = interleave({s: (lambda b=b: per_frame(b)) for s, b in batches.items()}, rep)
        for s, t in got.items():
            bench.add(f"s_per_frame_{s}", t)
    bench.finish()
