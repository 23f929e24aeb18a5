"""How long a supernet training step takes on this machine: what a time limit's plan sizes the supernet by.

A step costs more in the first part of a recipe: while progressive shrinking keeps every subnet at full
width (the first ``recipe.shrink`` of the steps), a step trains three full-width networks; after it,
one of them is the smallest and another a random width. So both phases are timed, a few steps each
after a warm-up, and weighted as the recipe runs them. A short run of the recipe timed mostly its
second half, and its median step took in the last step's empty interval (progress reports a step once
the next one has run), well short of the step the whole recipe took; ``bench_supernet_pace`` (the
training suite) compares both measurements with the whole recipe."""

from __future__ import annotations

import random
import statistics
import time
from typing import Iterator

import torch

from explorer.data import open_dataset
from explorer.data.resident import training_batches
from explorer.errors import UserError
from explorer.space import SearchSpace
from explorer.supernet._graphs import StageGraphs
from explorer.supernet.network import Supernet, largest_candidate, smallest_candidate
from explorer.supernet.train import SupernetRecipe, _sandwich_step, _shrinking, _subnets
from explorer.training.train import adamw


def seconds_per_step(space: SearchSpace, data: str, recipe: SupernetRecipe, accelerator: torch.device,
                     steps: int = 3, warmup: int = 2) -> float:
    """The mean seconds a step of ``recipe`` takes here over the whole recipe: ``steps`` steps of each of
    its phases (progressive shrinking, then every width) timed after ``warmup`` steps (a fresh process's
    first steps run 2x slower: allocation, first kernels), weighted by each phase's share of the steps.
    Nothing is written: the supernet trained here is thrown away."""
    torch.manual_seed(recipe.seed)
    net = Supernet(space).to(device=accelerator, memory_format=torch.channels_last)
    opt = adamw(net.parameters(), recipe.lr, recipe.weight_decay)
    train_set = open_dataset(data, "train", recipe.input_size, seed=recipe.seed)
    loader = training_batches(train_set, recipe.batch_size, torch.Generator().manual_seed(recipe.seed), accelerator)
    if len(loader) == 0:
        raise UserError(f"data {data}: {len(train_set)} training frames are fewer than --batch-size {recipe.batch_size}")
    batches = _endless(loader)
    graphs = StageGraphs() if recipe.cuda_graphs and accelerator.type == "cuda" else None
    largest, smallest = largest_candidate(space), smallest_candidate(space)

    def timed(step: int) -> float:
        subnets = _subnets(largest, smallest, space, recipe, step, random.Random(recipe.seed * 1_000_003 + step))
        t0 = time.perf_counter()
        _sandwich_step(net, opt, next(batches), subnets, recipe, accelerator, 0, 1, graphs).tolist()   # waits for it
        return time.perf_counter() - t0

    for step in range(warmup):
        timed(step)
    shrinking = sum(_shrinking(recipe, step) for step in range(recipe.steps))   # the first phase's steps
    seconds = 0.0
    for first, end in ((0, shrinking), (shrinking, recipe.steps)):
        if end > first:
            taken = [timed(first + k % (end - first)) for k in range(steps)]
            seconds += (end - first) / recipe.steps * statistics.median(taken)
    return seconds


def _endless(loader) -> Iterator[dict]:
    while True:
        yield from loader
