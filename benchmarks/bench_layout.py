"""Channels-last vs the default memory layout: one training step of the paper design and of the
supernet's largest subnet (batch 16 at 64x64), interleaved, 5 repetitions, every one printed and the
median; and the largest output difference between the two layouts.

    .venv/bin/python benchmarks/bench_layout.py
"""

import statistics
import time

import torch

from explorer.model import build_network
from explorer.space import SearchSpace, paper_candidate
from explorer.supernet import Supernet, largest_candidate
from explorer.training.train import multi_exit_loss

torch.set_num_threads(2)
torch.manual_seed(0)
image, scan, depth = torch.rand(16, 3, 64, 64), torch.rand(16, 64) * 5, torch.rand(16, 1, 64, 64) * 5
space = SearchSpace.from_yaml("anytime_depth")
largest = largest_candidate(space)
cases = {"paper design": build_network(paper_candidate()).train(), "supernet largest": Supernet(space).train()}


def step(net, layout) -> float:
    net.to(memory_format=layout)
    x = image.contiguous(memory_format=layout)
    t = time.perf_counter()
    outs = net.forward_subnet(largest, x, scan) if isinstance(net, Supernet) else net(x, scan)
    multi_exit_loss(outs, depth)[0].backward()
    return time.perf_counter() - t


for name, net in cases.items():
    step(net, torch.contiguous_format), step(net, torch.channels_last)   # warm-up
    plain, last = [], []
    for rep in range(5):
        plain.append(step(net, torch.contiguous_format))
        last.append(step(net, torch.channels_last))
        print(f"  {name} rep {rep + 1}: contiguous {plain[-1]:.3f} s, channels-last {last[-1]:.3f} s")
    print(f"{name}: median {statistics.median(plain):.3f} vs {statistics.median(last):.3f} s per step, "
          f"speed-up {statistics.median(plain) / statistics.median(last):.2f}x")
net = build_network(paper_candidate()).eval()
with torch.no_grad():
    a = net(image, scan)
    net.to(memory_format=torch.channels_last)
    b = net(image.contiguous(memory_format=torch.channels_last), scan)
print(f"largest output difference between layouts: {max(float((p - q).abs().max()) for p, q in zip(a, b)):.1e} m")
