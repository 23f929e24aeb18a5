"""Where the finalists retrain: in this process, or in worker processes, one per device.

A node with several GPUs retrains one finalist per GPU at once; one GPU retrains them one after
another in this process; on a CPU, ``--workers N`` processes split the cores. Workers only train:
each returns its finalist's metrics to this process, which alone
writes to the study (so SQLite, which takes one writer, serves parallel finalists too).
"""

from __future__ import annotations

import os
import signal
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Callable

import torch

from explorer.processes import die_with_parent
from explorer.training.train import resolve_accelerator


def finalist_devices(accelerator: str, workers: int) -> list[str]:
    """One entry per worker process, the torch device it trains on: every GPU when this machine has
    several (one finalist each, whatever ``workers``); the one GPU alone when it has one (a worker
    process spends longer starting CUDA and loading the data than two retrainings gain by sharing the
    GPU: bench_finalists); else ``workers`` processes sharing the CPU's cores."""
    device = resolve_accelerator(accelerator)
    if device.type == "cuda":
        return [f"cuda:{i}" for i in range(torch.cuda.device_count())] if torch.cuda.device_count() > 1 \
            else [f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}"]
    return [str(device)] * max(workers, 1)


class InProcess:
    """Runs each job here, when it is submitted (one worker, or one job)."""

    def __init__(self, make_objective: Callable[[], object], run_job: Callable) -> None:
        self.objective = make_objective()
        self.run_job = run_job

    def __enter__(self) -> "InProcess":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def submit(self, job) -> Future:
        future: Future = Future()
        try:
            future.set_result(self.run_job(self.objective, job))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller as the job's outcome
            future.set_exception(exc)
        return future


# -- worker processes -------------------------------------------------------------------------------
_WORKER: dict = {}


def _start_worker(devices, make_objective: Callable[[], object], threads: int) -> None:
    """A worker's start: its device (taken from the shared queue), its share of the cores, its data. It
    dies with its parent (kill -9 too) and leaves Ctrl-C to it (the parent ends the pool)."""
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    device = devices.get()
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
    torch.set_num_threads(max(threads, 1))
    objective = make_objective()
    objective.torch_device = torch.device(device)
    _WORKER["objective"] = objective


def _run_in_worker(run_job: Callable, job):
    return run_job(_WORKER["objective"], job)


class WorkerPool:
    """Jobs run in one spawned process per entry of ``devices``; ``submit`` returns at once."""

    def __init__(self, devices: list[str], make_objective: Callable[[], object], run_job: Callable) -> None:
        import multiprocessing as mp
        context = mp.get_context("spawn")    # CUDA cannot be used in forked children
        queue = context.Queue()
        for d in devices:
            queue.put(d)
        cpu = [d for d in devices if not d.startswith("cuda")]
        threads = max(1, (os.cpu_count() or 1) // max(len(cpu), 1))
        self.size = len(devices)
        self.run_job = run_job
        self.executor = ProcessPoolExecutor(len(devices), mp_context=context, initializer=_start_worker,
                                            initargs=(queue, make_objective, threads))

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, kind, *exc) -> None:
        if kind is not None and not issubclass(kind, Exception):   # Ctrl-C, SIGTERM: the jobs running are dropped
            for process in list((self.executor._processes or {}).values()):
                process.terminate()
        self.executor.shutdown(wait=True, cancel_futures=True)

    def submit(self, job) -> Future:
        return self.executor.submit(_run_in_worker, self.run_job, job)
