"""What the exit heads' export choices save: the last exit head up-sampling after its 1x1 layers
(``explorer.model.decoder``) and the bilinear up-sampling as two matrix products (``ops.Resize``), on
the paper design's whole graph and in PyTorch eager, against the paper's order with Resize operators;
then keeping the exit heads' resizes out of onnxruntime's blocked layout
(``explorer.model.ops.one_channel_unblocked``): the whole graph and each exit head alone, exported with
that step and without it. Each choice exists for speed; these figures say whether it still pays.

    python benchmarks/bench_exit_heads.py [--reps 5]

Each repetition times every variant, in interleaved blocks whose order rotates; the largest output
differences are in the record's notes.
"""

import io
from unittest import mock

import numpy as np
import torch
import torch.nn.functional as F

from explorer.calibration.measure import session
from explorer.model import build_network
from explorer.model.exits import ExitHead, ExitHeadConfig
from explorer.model.onnx import example_inputs, export_whole
from explorer.model.ops import Resize
from explorer.space import paper_candidate

from harness import Bench, time_interleaved

SIZE = (224, 224)
#: exit heads alone: (input channels, up-sampling factor, input side)
HEADS = ((256, 16, 14), (64, 8, 28), (32, 4, 56), (32, 2, 112))


def _interpolate(self, x: torch.Tensor) -> torch.Tensor:
    """``ops.Resize.forward`` as ``F.interpolate``: a Resize operator in the exported graph."""
    if self.factor == 1:
        return x
    kwargs = {"align_corners": False} if self.mode == "bilinear" else {}
    return F.interpolate(x, scale_factor=float(self.factor), mode=self.mode, **kwargs)


def _exported(fn, without: bool) -> bytes:
    if not without:
        return fn()
    with mock.patch("explorer.model.exits.one_channel_unblocked", lambda x: x):   # imported there by name
        return fn()


def order_and_products(bench: Bench) -> dict:
    """{variant: call}: the paper's order and the current one, as graphs and in eager."""
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    paper = build_network(paper_candidate(), paper_graph=True).eval()
    paper.load_state_dict(net.state_dict())
    feeds = {k: v.numpy() for k, v in example_inputs(SIZE).items()}
    img, scan = (torch.from_numpy(feeds[k]) for k in ("image", "scan"))
    with mock.patch("explorer.model.ops.Resize.forward", _interpolate):
        graphs = {"paper_resize": session(export_whole(paper, SIZE)),
                  "deferred_resize": session(export_whole(net, SIZE))}
    graphs["deferred_products"] = session(export_whole(net, SIZE))
    outs = {k: s.run(None, feeds) for k, s in graphs.items()}
    bench.note("largest difference per path against the paper's order with resizes: " + "; ".join(
        f"{k} " + " ".join(f"{float(np.abs(a - b).max()):.1e}" for a, b in zip(o, outs["paper_resize"]))
        for k, o in outs.items() if k != "paper_resize"))

    def eager(model, forward):
        def run():   # both patched, so that both pay the patching
            with torch.no_grad(), mock.patch("explorer.model.ops.Resize.forward", forward):
                model(img, scan)
        return run
    return {**{k: (lambda s=s: s.run(None, feeds)) for k, s in graphs.items()},
            "eager_paper": eager(paper, _interpolate), "eager_current": eager(net, Resize.forward)}


def unblocked(bench: Bench) -> dict:
    """{variant: call}: the whole graph and each exit head, with and without the unblocked resizes."""
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    feeds = {k: v.numpy() for k, v in example_inputs(SIZE).items()}
    whole = {w: session(_exported(lambda: export_whole(net, SIZE), w)) for w in (False, True)}
    same = all(np.allclose(a, b, rtol=1e-4, atol=1e-4) for a, b in zip(*(s.run(None, feeds) for s in whole.values())))
    bench.note(f"whole graph with and without the unblocked exit resizes: same outputs {same}")
    fns = {f"whole_{'without' if w else 'with'}": (lambda s=s: s.run(None, feeds)) for w, s in whole.items()}
    for cin, up, hw in HEADS:
        torch.manual_seed(0)
        head = ExitHead(ExitHeadConfig(in_channels=cin, depth=1, width=cin, upscale=up)).eval()
        x = torch.rand(1, cin, hw, hw)

        def export(head=head, x=x) -> bytes:
            f = io.BytesIO()
            torch.onnx.export(head, (x,), f, input_names=["x"], output_names=["depth"], dynamo=False)
            return f.getvalue()
        for w in (False, True):
            s = session(_exported(export, w))
            fns[f"head{cin}x{hw}_{'without' if w else 'with'}"] = lambda s=s, x=x.numpy(): s.run(None, {"x": x})
    return fns


def declare(bench: Bench) -> None:
    for key, label in (("paper_resize", "whole graph, paper order with Resize"),
                       ("deferred_resize", "whole graph, deferred up-sampling with Resize"),
                       ("deferred_products", "whole graph, deferred up-sampling as products"),
                       ("eager_paper", "eager, paper order with F.interpolate"),
                       ("eager_current", "eager, current model")):
        bench.figure(f"{key}_ms", label, "ms", "lower")
    bench.figure("deferred_products_change", "whole graph, current against paper order (time ratio - 1)", "", "lower")
    bench.figure("eager_over_onnxruntime", "eager / onnxruntime, current model", "x", None)
    bench.figure("whole_with_ms", "whole graph with unblocked exit resizes", "ms", "lower")
    bench.figure("whole_without_ms", "whole graph without unblocked exit resizes", "ms", "lower")
    bench.figure("whole_without_over_with", "whole graph: without / with unblocked resizes", "x", "higher")
    for cin, up, hw in HEADS:
        bench.figure(f"head{cin}x{hw}_with_us", f"exit head {cin} ch at {hw}x{hw} x{up}, with", "us", "lower")
        bench.figure(f"head{cin}x{hw}_without_us", f"exit head {cin} ch at {hw}x{hw} x{up}, without", "us", "lower")
        bench.figure(f"head{cin}x{hw}_without_over_with", f"exit head {cin} ch at {hw}x{hw}: without / with", "x",
                     "higher")


if __name__ == "__main__":
    bench = Bench(__file__, "Exit heads: up-sampling order, Resize as products, unblocked resizes", __doc__, reps=5)
    args = bench.parse_args(bench.parser())
    first, second = order_and_products(bench), unblocked(bench)
    declare(bench)
    for rep in bench.repetitions():
        ms = time_interleaved(first, rep, blocks=5)
        for k in first:
            bench.add(f"{k}_ms", ms[k])
        bench.add("deferred_products_change", ms["deferred_products"] / ms["paper_resize"] - 1)
        bench.add("eager_over_onnxruntime", ms["eager_current"] / ms["deferred_products"])
        ms = time_interleaved(second, rep, blocks=5, per_block=8)
        bench.add("whole_with_ms", ms["whole_with"])
        bench.add("whole_without_ms", ms["whole_without"])
        bench.add("whole_without_over_with", ms["whole_without"] / ms["whole_with"])
        for cin, _, hw in HEADS:
            w, wo = ms[f"head{cin}x{hw}_with"], ms[f"head{cin}x{hw}_without"]
            bench.add(f"head{cin}x{hw}_with_us", 1000 * w)
            bench.add(f"head{cin}x{hw}_without_us", 1000 * wo)
            bench.add(f"head{cin}x{hw}_without_over_with", wo / w)
    bench.finish()
