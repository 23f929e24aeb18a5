"""Ctrl-C (or SIGTERM) of `explorer train` and `explorer supernet train` before their first checkpoint
keeps the weights reached, saved atomically at the end of the step running, and the same command resumes
from them (issue 89). Each waits for the training's own progress lines, not for a time."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
import torch

from explorer.space import SearchSpace
from conftest import TINY_DATA

STEPS = "100000"     # never reached: the first checkpoint would come at the end


def _started(tmp_path, *args: str) -> tuple[subprocess.Popen, list[str]]:
    """The command running, and its stderr lines as they come (progress lines every 0.2 s)."""
    proc = subprocess.Popen([sys.executable, "-m", "explorer", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env={**os.environ, "EXPLORER_PROGRESS_EVERY": "0.2"})
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True).start()
    return proc, lines


def _wait_for_steps(proc: subprocess.Popen, lines: list[str], task: str) -> None:
    """Until a progress line says that ``task`` has done a step."""
    pattern = re.compile(rf"^{re.escape(task)}: (\d+)/{STEPS} done")
    deadline = time.time() + 600
    while not any((m := pattern.match(line)) and int(m.group(1)) >= 1 for line in list(lines)):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"{task} never made a step: {lines} {proc.communicate()[0]}")
        time.sleep(0.05)


def _ended(proc: subprocess.Popen, lines: list[str]) -> str:
    """The last line on stderr, once the command ended (no traceback before it)."""
    out = proc.communicate(timeout=300)[0]
    time.sleep(0.1)   # the reader thread's last line
    err = "".join(lines)
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line.strip()][-1] if err.strip() else out


@pytest.mark.slow
def test_ctrl_c_of_train_keeps_the_weights_and_the_same_command_resumes(tmp_path):
    candidate = tmp_path / "cand.yaml"
    candidate.write_text(next(SearchSpace.from_yaml("tiny").enumerate()).to_yaml())
    ckpt = tmp_path / "out" / "ck.pt"
    args = ["train", candidate, "--data", TINY_DATA, "--batch-size", "8", "--train-size", "32x32", "--out", ckpt]
    proc, lines = _started(tmp_path, *args, "--steps", STEPS)
    _wait_for_steps(proc, lines, "training (supervised)")
    proc.send_signal(signal.SIGINT)
    last = _ended(proc, lines)
    assert proc.returncode == 130, lines
    step = torch.load(ckpt, weights_only=True)["step"]
    assert last == (f"explorer: interrupted; the weights at step {step} of {STEPS} are saved in {ckpt}: run the same "
                    "command again to resume from there")
    assert step >= 1 and [p.name for p in ckpt.parent.iterdir()] == ["ck.pt"]    # no scratch left beside it
    # the same command resumes: asked for the steps already done, it trains none (0 images a second)
    again = subprocess.run([sys.executable, "-m", "explorer", *map(str, args), "--steps", str(step)],
                           capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"saved {ckpt} ({step} steps, 0.0 images/s)" in again.stdout


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_supernet_training_keeps_its_weights_and_resumes(tmp_path, sig):
    out = tmp_path / "sn.pt"
    args = ["supernet", "train", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--batch-size", "8",
            "--steps", STEPS, "--checkpoint-every", STEPS, "--out", out]
    proc, lines = _started(tmp_path, *args)
    _wait_for_steps(proc, lines, "supernet")
    proc.send_signal(sig)
    last = _ended(proc, lines)
    from explorer.supernet.train import read
    step = read(out)["step"]
    assert step >= 1
    if sig == signal.SIGINT:
        assert proc.returncode == 130
        assert last == (f"explorer: interrupted; the supernet's weights at step {step} of {STEPS} are saved in {out}: "
                        "run the same command again to resume from there")
    else:
        assert proc.returncode == 128 + signal.SIGTERM
    again = subprocess.run([sys.executable, "-m", "explorer", *map(str, args), "--stop-after-steps", "1"],
                           capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
    assert read(out)["step"] == step + 1      # resumed from the step saved, not from 0
