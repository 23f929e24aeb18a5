"""The optimizer step of supernet training: PyTorch's AdamW as it comes (a loop over the tensors on
the CPU, grouped "foreach" kernels on CUDA) against the fused AdamW that training uses
(:func:`explorer.training.train.adamw`), over the default space's supernet parameters with gradients
on every tensor.

    python benchmarks/bench_optimizer.py [--reps 3] [--device cpu|cuda] [--threads 2]

Each repetition times both, in an order that rotates (10 rounds of 4 timed steps each, the median),
and records milliseconds a step and their ratio.
"""

import torch

from explorer.space import SearchSpace
from explorer.supernet import Supernet

from harness import Bench, time_interleaved


def optimizers(device: torch.device) -> dict:
    """{"plain": AdamW with PyTorch's defaults, "fused": the fused AdamW}, each over its own copy of the
    supernet's parameters, every one with a gradient."""
    out = {}
    for name, fused in (("plain", None), ("fused", True)):
        torch.manual_seed(0)
        params = list(Supernet(SearchSpace.from_yaml("anytime_depth")).to(device).parameters())
        for p in params:
            p.grad = torch.randn_like(p) * 1e-3
        out[name] = torch.optim.AdamW(params, lr=2e-3, weight_decay=1e-4, fused=fused)
    return out


def main() -> None:
    bench = Bench(__file__, "AdamW step over the supernet's parameters: as it comes and fused", __doc__)
    ap = bench.parser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, default=2, help="torch threads on the CPU")
    args = bench.parse_args(ap)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    opts = optimizers(device)

    def stepper(opt):
        def step():
            opt.step()
            if device.type == "cuda":
                torch.cuda.synchronize()
        return step

    fns = {name: stepper(opt) for name, opt in opts.items()}
    n = sum(p.numel() for p in opts["plain"].param_groups[0]["params"])
    bench.note(f"{len(opts['plain'].param_groups[0]['params'])} tensors, {n / 1e6:.2f} M parameters, on {device}")
    plain = bench.figure("plain_ms", "AdamW as it comes", "ms", "lower")
    fused = bench.figure("fused_ms", "fused AdamW", "ms", "lower")
    ratio = bench.figure("speedup", "as it comes / fused", "x", "higher")
    for rep in bench.repetitions():
        ms = time_interleaved(fns, rep)
        bench.add(plain, ms["plain"])
        bench.add(fused, ms["fused"])
        bench.add(ratio, ms["plain"] / ms["fused"])
    bench.finish()


if __name__ == "__main__":
    main()
