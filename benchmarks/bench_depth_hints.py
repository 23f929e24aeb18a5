"""What depth hints cost to compute (issue 13): seconds per frame of :func:`explorer.training.depth_hints.compute_hints`
(200 Adam steps, a batch of 16 frames as ``with_hints`` runs them) at each input size, sizes interleaved,
every repetition and the median printed. Multiply by the training frames for the one-off cost before a
``--depth-hints`` training or study (cached afterwards).

    .venv/bin/python benchmarks/bench_depth_hints.py [--sizes 64,112] [--repeats 3]
"""

import argparse
import statistics
import time

import torch
from torch.utils.data import DataLoader

from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.training.depth_hints import BATCH, STEPS, compute_hints

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="64,112", help="square input sizes, comma-separated")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(2)
    sizes = [int(s) for s in args.sizes.split(",")]
    # rendered at 128x128 (bench_selfsup's data); larger sizes are upsampled, which costs the same per pixel
    source = SyntheticSequences(ensure_synthetic_sequences(SyntheticSequenceConfig(train=480, val=48, height=128,
                                                                                   width=128)), "val")
    batches = {s: next(iter(DataLoader(SequenceDataset(source, (s, s)), batch_size=BATCH))) for s in sizes}
    times: dict[int, list[float]] = {s: [] for s in sizes}
    for rep in range(args.repeats):
        for s, batch in batches.items():
            t0 = time.perf_counter()
            compute_hints(batch)
            times[s].append((time.perf_counter() - t0) / BATCH)
            print(f"rep {rep} {s}x{s}: {times[s][-1]:.3f} s per frame", flush=True)
    print(f"\n{STEPS} steps, batches of {BATCH}, 2 threads; medians over {args.repeats} repetitions:")
    for s, t in times.items():
        print(f"  {s}x{s}: {statistics.median(t):.3f} s per frame ({' / '.join(format(x, '.3f') for x in t)}); "
              f"1,200 frames (synthetic-seq's default) {1200 * statistics.median(t) / 60:.0f} min once")
