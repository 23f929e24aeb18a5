"""CUDA graphs of a supernet's stages, for training on a GPU.

At the default recipe (64x64, batches of 16) a GPU finishes each of a step's thousands of small
kernels sooner than Python and PyTorch's dispatcher can launch the next one: the step's time is the
host's, and the GPU idles (bench_gpu). A CUDA graph launches a whole stage's forward
(or backward) pass at once. A subnet is a random combination of stages, but few distinct stage
configurations make up all of them (a stage name, its config, its input shapes): each is captured the
first time it runs and replayed whenever a subnet has it again.

A stage's graph reads the supernet's own tensors, sliced inside it (the optimizer updates them in
place, so the addresses the graph captured stay valid). Its backward graph adds the gradients of those
tensors into accumulators of its own, also inside the graph: no per-tensor gradient bookkeeping is left
on the host. :meth:`StageGraphs.gradients_to` hands the accumulated gradients to the parameters before
the optimizer step, only of the parameters some stage used (the others keep no gradient, so the
optimizer leaves them alone, as without graphs). A capture first runs the stage twice, outside the
graph (cuDNN and cuBLAS choose their kernels there), and restores the BatchNorm statistics those runs
moved, so training with graphs updates the weights as training without them does.

``emulate=True`` replays by running the stage again (on any device), with the same static buffers and
accumulators: the tests check the bookkeeping on a CPU against training without graphs.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from contextlib import nullcontext
from typing import Callable, Hashable, Sequence

import torch

#: runs of a stage before its capture (cuDNN's and cuBLAS's choices and lazy initialisation happen there)
WARMUP_RUNS = 2


def _signature(x: torch.Tensor) -> tuple:
    return tuple(x.shape), x.stride(), x.dtype, x.requires_grad


def _static_copy(x: torch.Tensor) -> torch.Tensor:
    """A buffer of its own holding ``x`` (dense: an expanded view's values, in a tensor of its shape)."""
    static = torch.empty_like(x, memory_format=torch.preserve_format)
    static.copy_(x.detach())
    return static.requires_grad_(x.requires_grad)


class _StageGraph:
    """One stage configuration's forward and backward passes, captured (or emulated)."""

    def __init__(self, fn: Callable[..., tuple[torch.Tensor, ...]], inputs: Sequence[torch.Tensor],
                 params: Sequence[torch.Tensor], buffers: Sequence[torch.Tensor],
                 accumulators: Callable[[torch.Tensor], torch.Tensor], emulate: bool) -> None:
        self.fn, self.emulate = fn, emulate
        self.static_in = [_static_copy(x) for x in inputs]
        self.params = list(params)
        self.used: list[torch.Tensor] = []      # the params the stage's gradients reach (found by the warm-up)
        outs = self._warm_up(buffers)
        self.accumulators = accumulators
        if emulate:
            self.static_out = [o.detach().clone() for o in outs]
        else:
            self._capture()

    def _grad_inputs(self) -> list[torch.Tensor]:
        """The inputs that take gradients, then the params: ``autograd.grad``'s order here."""
        return [x for x in self.static_in if x.requires_grad] + self.params

    @property
    def _n_grad_inputs(self) -> int:
        return sum(x.requires_grad for x in self.static_in)

    def _run(self) -> tuple[torch.Tensor, ...]:
        with torch.enable_grad():
            return self.fn(*self.static_in)

    def _warm_up(self, buffers: Sequence[torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """The stage's last outputs of ``WARMUP_RUNS`` runs, whose changes to ``buffers`` are undone."""
        saved = [b.clone() for b in buffers]
        side = torch.cuda.Stream() if not self.emulate else None
        if side is not None:
            side.wait_stream(torch.cuda.current_stream())
        try:
            with torch.cuda.stream(side) if side is not None else nullcontext():
                for _ in range(WARMUP_RUNS):
                    outs = self._run()
                    needed = [o for o in outs if o.requires_grad]
                    grads = torch.autograd.grad(needed, self._grad_inputs(), [torch.zeros_like(o) for o in needed],
                                                allow_unused=True)
        finally:   # a stage that fails here leaves the statistics as it found them
            if side is not None:
                torch.cuda.current_stream().wait_stream(side)
            with torch.no_grad():
                for b, s in zip(buffers, saved):
                    b.copy_(s)
        self.used = [p for p, g in zip(self.params, grads[self._n_grad_inputs:]) if g is not None]
        return outs

    def _capture(self) -> None:
        self.forward_graph, self.backward_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.forward_graph):
            outs = self._run()
        self.static_out = list(outs)
        self.static_grad_out = [torch.empty_like(o) for o in outs]
        needed = [(o, g) for o, g in zip(outs, self.static_grad_out) if o.requires_grad]
        with torch.cuda.graph(self.backward_graph, pool=self.forward_graph.pool()):
            self.static_grad_in = self._backward([o for o, _ in needed], [g for _, g in needed])

    def _backward(self, outs: list[torch.Tensor], grad_outs: list[torch.Tensor]) -> list[torch.Tensor | None]:
        """The inputs' gradients; the params' are added to their accumulators."""
        n = self._n_grad_inputs
        grads = torch.autograd.grad(outs, self._grad_inputs(), grad_outs, allow_unused=True)
        pairs = [(self.accumulators(p), g) for p, g in zip(self.params, grads[n:]) if g is not None]
        if pairs:
            torch._foreach_add_([a for a, _ in pairs], [g for _, g in pairs])
        return list(grads[:n])

    def forward(self, inputs: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        for static, x in zip(self.static_in, inputs):
            if static.data_ptr() != x.data_ptr():
                static.copy_(x)
        if self.emulate:
            self._live = self._run()
            for static, o in zip(self.static_out, self._live):
                static.copy_(o.detach())
        else:
            self.forward_graph.replay()
        return [o.detach() for o in self.static_out]

    def backward(self, grads: Sequence[torch.Tensor]) -> list[torch.Tensor | None]:
        if self.emulate:
            needed = [(o, g) for o, g in zip(self._live, grads) if o.requires_grad]
            with torch.enable_grad():
                return self._backward([o for o, _ in needed], [g for _, g in needed])
        for static, g in zip(self.static_grad_out, grads):
            if static.data_ptr() != g.data_ptr():
                static.copy_(g)
        self.backward_graph.replay()
        return [g.detach() for g in self.static_grad_in]


class _Replay(torch.autograd.Function):
    """A stage's graph as one autograd node. One of the stage's params comes in (``anchor``) only so
    that the outputs require grad even where no input does (the first stage): the params' gradients go
    to the accumulators, not through autograd."""

    @staticmethod
    def forward(ctx, graph: _StageGraph, anchor: torch.Tensor, *inputs: torch.Tensor):
        ctx.graph = graph
        ctx.grad_inputs = [x.requires_grad for x in inputs]
        return tuple(graph.forward(inputs))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads: torch.Tensor):
        got = iter(ctx.graph.backward(grads))
        return (None, None, *[next(got) if needs else None for needs in ctx.grad_inputs])


class StageGraphs:
    """The captured stages of one supernet training run, and the gradients their replays accumulate.

    ``run`` replays the graph of ``key`` (capturing it the first time); after a step's backward passes,
    ``gradients_to`` gives the params their gradients and ``clear`` readies the accumulators for the
    next step. At most ``limit`` graphs are kept (the least recently used go first): each holds its
    stage's activations. Should a capture fail (an operation or a driver that CUDA graphs do not
    support), a warning says so and the run goes on without graphs, as ``--no-cuda-graphs`` trains."""

    def __init__(self, emulate: bool = False, limit: int = 1024) -> None:
        self.emulate, self.limit = emulate, limit
        self.graphs: OrderedDict[Hashable, _StageGraph] = OrderedDict()
        # id(param) -> (param, sum): the param is held so that its id stays its own
        self._accumulators: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._touched: dict[int, torch.Tensor] = {}
        self.captures = 0
        self.failed = ""     # why a capture failed: the rest of the run trains without graphs

    def _accumulator(self, param: torch.Tensor) -> torch.Tensor:
        if id(param) not in self._accumulators:
            self._accumulators[id(param)] = (param, torch.zeros_like(param, memory_format=torch.preserve_format))
        return self._accumulators[id(param)][1]

    def run(self, key: Hashable, fn: Callable[..., tuple[torch.Tensor, ...]], inputs: Sequence[torch.Tensor],
            params: Sequence[torch.Tensor], buffers: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """``fn(*inputs)``'s outputs, differentiable in ``inputs`` and (through the accumulators) in
        ``params``. ``key`` names everything the graph depends on besides ``inputs``' values (the stage,
        its config, the inputs' shapes and the mode); ``buffers``: the tensors ``fn`` changes in place."""
        if self.failed:
            return list(fn(*inputs))
        key = (key, tuple(_signature(x) for x in inputs), torch.is_autocast_enabled("cuda"),
               torch.is_autocast_enabled("cpu"), torch.is_grad_enabled())
        graph = self.graphs.get(key)
        if graph is None:
            self._make_room()
            for p in params:
                self._accumulator(p)   # allocated outside the graph's memory
            try:
                graph = _StageGraph(fn, inputs, params, buffers, self._accumulator, self.emulate)
            except Exception as exc:   # PyTorch raises several types for what it cannot capture
                self.failed = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160] if str(exc) else ''}"
                warnings.warn(f"CUDA graphs: capturing a stage failed ({self.failed}); this run goes on "
                              "without them", RuntimeWarning, stacklevel=2)
                self.graphs.clear()
                return list(fn(*inputs))
            self.captures += 1
            self.graphs[key] = graph
            if len(self.graphs) > self.limit:
                self.graphs.popitem(last=False)
        self.graphs.move_to_end(key)
        for p in graph.used:
            self._touched[id(p)] = p
        return list(_Replay.apply(graph, params[0], *inputs))

    def _make_room(self) -> None:
        """Before a capture on a GPU with under a quarter of its memory free, the least recently used
        quarter of the graphs (each holds its stage's activations) is let go."""
        if self.emulate or not self.graphs:
            return
        free, total = torch.cuda.mem_get_info()
        if free >= total / 4:
            return
        for _ in range(max(1, len(self.graphs) // 4)):
            self.graphs.popitem(last=False)
        torch.cuda.empty_cache()

    def gradients_to(self) -> None:
        """The step's accumulated gradients, given to the params the step's stages used (added to any
        gradient they already have)."""
        for key, p in self._touched.items():
            total = self._accumulators[key][1]
            if p.grad is None:
                p.grad = total
            else:
                p.grad.add_(total)

    def clear(self) -> None:
        """After the optimizer step: the accumulators zeroed, and the params' gradients dropped."""
        totals = [self._accumulators[k][1] for k in self._touched]
        if totals:
            torch._foreach_zero_(totals)
        for p in self._touched.values():
            p.grad = None
        self._touched = {}
