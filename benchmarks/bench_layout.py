"""Channels-last against the default memory layout for training: one training step (forward and
backward, batch 16 at 64x64) of the paper design and of the supernet's largest subnet. PyTorch's CPU
convolutions can be faster on channels-last tensors; this says whether training should use it here.

    python benchmarks/bench_layout.py [--reps 5]

Both layouts alternate within each repetition; the largest output difference between the two layouts
is in the record's notes.
"""

import time

import torch

from explorer.model import build_network
from explorer.space import SearchSpace, paper_candidate
from explorer.supernet import Supernet, largest_candidate
from explorer.training.train import multi_exit_loss

from harness import Bench, interleave

LAYOUTS = {"contiguous": torch.contiguous_format, "channels_last": torch.channels_last}


def step(net, layout, largest, image, scan, depth) -> float:
    """Seconds of one forward and backward pass in ``layout``."""
    net.to(memory_format=layout)
    x = image.contiguous(memory_format=layout)
    t = time.perf_counter()
    outs = net.forward_subnet(largest, x, scan) if isinstance(net, Supernet) else net(x, scan)
    multi_exit_loss(outs, depth)[0].backward()
    return time.perf_counter() - t


def largest_difference(image, scan) -> float:
    net = build_network(paper_candidate()).eval()
    with torch.no_grad():
        a = net(image, scan)
        net.to(memory_format=torch.channels_last)
        b = net(image.contiguous(memory_format=torch.channels_last), scan)
    return max(float((p - q).abs().max()) for p, q in zip(a, b))


if __name__ == "__main__":
    bench = Bench(__file__, "Channels-last against contiguous layout: training step time", __doc__, reps=5)
    args = bench.parse_args(bench.parser())
    torch.set_num_threads(2)
    torch.manual_seed(0)
    image, scan, depth = torch.rand(16, 3, 64, 64), torch.rand(16, 64) * 5, torch.rand(16, 1, 64, 64) * 5
    space = SearchSpace.from_yaml("anytime_depth")
    largest = largest_candidate(space)
    cases = {"paper": ("paper design", build_network(paper_candidate()).train()),
             "supernet": ("supernet largest subnet", Supernet(space).train())}
    for key, (label, net) in cases.items():
        for layout in LAYOUTS.values():   # warm-up
            step(net, layout, largest, image, scan, depth)
        bench.figure(f"{key}_contiguous_s", f"{label}, contiguous", "s", "lower")
        bench.figure(f"{key}_channels_last_s", f"{label}, channels-last", "s", "lower")
        bench.figure(f"{key}_speedup", f"{label}: contiguous / channels-last", "x", "higher")
    bench.note(f"largest output difference between layouts {largest_difference(image, scan):.1e} m; 2 threads")
    for rep in bench.repetitions():
        for key, (_, net) in cases.items():
            got = interleave({k: (lambda lay=lay: step(net, lay, largest, image, scan, depth))
                              for k, lay in LAYOUTS.items()}, rep)
            bench.add(f"{key}_contiguous_s", got["contiguous"])
            bench.add(f"{key}_channels_last_s", got["channels_last"])
            bench.add(f"{key}_speedup", got["contiguous"] / got["channels_last"])
    bench.finish()
