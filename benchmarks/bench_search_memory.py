"""Peak memory of `make search`'s job: ``explorer search --device tx2 --time-limit L`` on the embedded
default data, each repetition in a fresh folder with a fresh cache (its supernet trained anew), the
resident memory (RSS) of its whole process tree sampled every 0.2 s. A laptop with 8 GB must run it
beside a desktop; the target is under 3 GB. The default data is generated once, before the
repetitions (it takes a few minutes and little memory), so the limit goes to the phases that hold
memory: measuring the machine (a few steps at 224x224), the supernet's training, sampling (the
evaluator's stage memo and encoder features) and the finalists' retraining and tuning at 224x224.

    python benchmarks/bench_search_memory.py [--reps 3] [--time-limit 700] [--threads 1]

``--time-limit 700`` is what `make search`'s 960 s leave after generating the data on a 2-core machine.
About 12 minutes a repetition.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import ROOT, Bench  # noqa: E402

SAMPLE_S = 0.2


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            kids.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry))
    return kids


def _rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def tree_rss(root: int) -> int:
    """The summed RSS of ``root`` and every process below it (worker processes count too)."""
    kids, todo, total = _children(), [root], 0
    while todo:
        pid = todo.pop()
        total += _rss_bytes(pid)
        todo += kids.get(pid, [])
    return total


def run_sampled(cmd: list[str], cwd: Path, env: dict) -> tuple[int, float, float, float, str]:
    """(exit code, peak tree RSS in bytes, seconds into the run it was reached, wall seconds, output tail)."""
    log = cwd / "search.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        t0, peak, peak_at = time.time(), 0, 0.0
        while proc.poll() is None:
            rss = tree_rss(proc.pid)
            if rss > peak:
                peak, peak_at = rss, time.time() - t0
            time.sleep(SAMPLE_S)
        wall = time.time() - t0
    tail = "\n".join(log.read_text(errors="replace").replace("\r", "\n").splitlines()[-12:])
    return proc.returncode, peak, peak_at, wall, tail


def generate_data(cache: Path) -> Path:
    """The default data set generated into ``cache`` (untimed); its file."""
    code = ("from explorer.data.synthetic import SyntheticConfig, ensure_synthetic; "
            "print(ensure_synthetic(SyntheticConfig()))")
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(cache)}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    return Path(out.stdout.strip().splitlines()[-1])


def one_run(bench: Bench, data: Path, limit_s: int, threads: int, rep: int) -> None:
    work = Path(tempfile.mkdtemp(prefix="bench-search-memory-"))
    try:
        cache = work / "cache"
        cache.mkdir()
        (cache / data.name).symlink_to(data)          # the data, not the supernet: that is trained anew
        env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(cache), "PYTHONUNBUFFERED": "1"}
        if threads:
            env["OMP_NUM_THREADS"] = str(threads)
        cmd = [sys.executable, "-m", "explorer", "search", "--device", "tx2", "--time-limit", str(limit_s)]
        code, peak, peak_at, wall, tail = run_sampled(cmd, work, env)
        print(f"  rep {rep}: exit {code}, {wall:.0f} s, peak {peak / 1e9:.2f} GB at {peak_at:.0f} s\n{tail}",
              flush=True)
        if code != 0:
            raise SystemExit(f"explorer search failed (exit {code}):\n{tail}")
        bench.add("peak_rss_gb", peak / 1e9)
        bench.add("peak_at", peak_at / wall)
        bench.add("wall_s", wall)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    bench = Bench(__file__, "make search's peak memory (RSS of the process tree)", __doc__)
    ap = bench.parser()
    ap.add_argument("--time-limit", type=int, default=700, help="the search's --time-limit in seconds")
    ap.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS for the search (0: as make search, "
                    "the free cores)")
    args = bench.parse_args(ap)
    bench.figure("peak_rss_gb", "peak RSS of the search's process tree (target under 3 GB)", "GB", "lower")
    bench.figure("peak_at", "when the peak came, as a share of the run's wall time", "", None)
    bench.figure("wall_s", "the search's wall time", "s", None)
    data_dir = Path(tempfile.mkdtemp(prefix="bench-search-memory-data-"))
    try:
        t0 = time.time()
        data = generate_data(data_dir)
        print(f"default data generated in {time.time() - t0:.0f} s: {data}", flush=True)
        for rep in bench.repetitions():
            one_run(bench, data, args.time_limit, args.threads, rep)
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)
    peaks = bench.figures["peak_rss_gb"].reps
    print(f"peak RSS per repetition: {', '.join(f'{p:.2f}' for p in peaks)} GB; "
          f"median {statistics.median(peaks):.2f} GB")
    bench.note(f"explorer search --device tx2 --time-limit {args.time_limit} (make search's job; its 960 s less "
               f"the data's generation, done once before the repetitions), OMP_NUM_THREADS="
               f"{args.threads or 'unset'}, {os.cpu_count()} cores; RSS summed over the process tree every "
               f"{SAMPLE_S} s; the checkout's code ({ROOT.name}), a fresh cache and supernet each repetition")
    bench.finish()
