"""Signals (issue 89): Ctrl-C (or SIGTERM) of `explorer train` and `explorer supernet train` before their
first checkpoint keeps the weights reached, saved atomically at the end of the step running, and the same
command resumes from them; Ctrl-C of a search, once or twice, is one line saying what the study kept and
how to resume, exit 130, no traceback; SIGTERM unwinds like Ctrl-C and leaves no scratch (a generation,
a calibration). Each waits for the command's own progress or state, not for a time."""

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
from explorer.study._stopping import _QuietCtrlC
from conftest import TINY_DATA, journal_trials
from _faults import running, says_one_line, search_process, wait_for

STEPS = "100000"     # never reached: the first checkpoint would come at the end


def _started(tmp_path, *args: str) -> tuple[subprocess.Popen, list[str]]:
    """The command running, and its stderr lines as they come (progress lines every 0.2 s). One thread
    reads each pipe to its end, so that nothing else reads stderr and takes lines from ``lines``."""
    proc = subprocess.Popen([sys.executable, "-m", "explorer", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env={**os.environ, "EXPLORER_PROGRESS_EVERY": "0.2"})
    lines: list[str] = []
    proc.out = []
    proc.readers = [threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True),
                    threading.Thread(target=lambda: proc.out.append(proc.stdout.read()), daemon=True)]
    for reader in proc.readers:
        reader.start()
    return proc, lines


def _wait_for_steps(proc: subprocess.Popen, lines: list[str], task: str) -> None:
    """Until a progress line says that ``task`` has done a step."""
    pattern = re.compile(rf"^{re.escape(task)}: (\d+)/{STEPS} done")
    deadline = time.time() + 600
    while not any((m := pattern.match(line)) and int(m.group(1)) >= 1 for line in list(lines)):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"{task} never made a step: {lines}")
        time.sleep(0.05)


def _ended(proc: subprocess.Popen, lines: list[str]) -> str:
    """The last line on stderr, once the command ended (no traceback before it)."""
    try:
        proc.wait(timeout=300)
    except subprocess.TimeoutExpired:
        proc.kill()    # a command that did not stop is not left running after the test
        raise
    for reader in proc.readers:
        reader.join(timeout=60)   # every line the command wrote, however busy the machine
    err = "".join(lines)
    assert "Traceback" not in err, err
    said = [line for line in err.splitlines() if line.strip()]
    return said[-1] if said else "".join(proc.out)


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


@pytest.mark.slow
def test_a_generation_stopped_by_sigterm_leaves_nothing_after_the_next_start(tmp_path):
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(tmp_path)}
    code = "from explorer.data import open_dataset; open_dataset('synthetic:600:100', 'train', (64, 64))"
    child = subprocess.Popen([sys.executable, "-c", code], env=env)
    deadline = time.time() + 120
    while time.time() < deadline and not any(".tmp" in p.name for p in tmp_path.iterdir()):
        time.sleep(0.1)
    child.send_signal(signal.SIGTERM)
    child.wait()
    subprocess.run([sys.executable, "-c", code.replace("600:100", "8:4")], env=env, check=True)
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]


SCRATCH_THEN_WAIT = ("import sys, time\n"
                     "from explorer.files import scratch_dir, sigterm_unwinds\n"
                     "with sigterm_unwinds(), scratch_dir('calibrate') as tmp:\n"
                     "    open(tmp + '/results.json', 'w').write('{}')\n"
                     "    print(tmp, flush=True)\n"
                     "    time.sleep(120)\n")


def test_sigterm_unwinds_and_leaves_no_scratch_folder(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", SCRATCH_THEN_WAIT], env={**os.environ, "TMPDIR": str(tmp_path)},
                             stdout=subprocess.PIPE, text=True)
    folder = child.stdout.readline().strip()
    assert os.path.isdir(folder) and os.path.dirname(folder) == str(tmp_path)
    child.send_signal(signal.SIGTERM)
    assert child.wait(timeout=60) == 128 + signal.SIGTERM
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_a_calibration_stopped_by_sigterm_leaves_nothing_in_the_temporary_folder(tmp_path):
    """`explorer calibrate`, stopped while it exports its graphs into its scratch folder: the folder
    goes with it."""
    env = {**os.environ, "TMPDIR": str(tmp_path / "tmp"), "OMP_NUM_THREADS": "1"}
    (tmp_path / "tmp").mkdir()
    with open(tmp_path / "stderr", "w") as err:
        child = subprocess.Popen([sys.executable, "-m", "explorer", "calibrate", "--quick", "--out",
                                  str(tmp_path / "p.yaml")], env=env, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.time() + 120
    while (time.time() < deadline and child.poll() is None
           and not any((tmp_path / "tmp").glob(f"explorer-{child.pid}-calibrate-*/bundle"))):
        time.sleep(0.1)
    assert child.poll() is None, (tmp_path / "stderr").read_text()[-2000:]
    child.send_signal(signal.SIGTERM)
    assert child.wait(timeout=60) == 128 + signal.SIGTERM
    # (onnxruntime keeps a small file of its own there)
    assert not list((tmp_path / "tmp").glob("explorer-*")) and not (tmp_path / "p.yaml").exists()


@pytest.mark.slow
@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_of_a_search_is_one_line_and_keeps_the_study(tmp_path, presses):
    journal = tmp_path / "s" / "journal.log"
    proc = search_process(tmp_path)
    wait_for(proc, lambda: running(journal) >= 1, "a trial in training")
    for _ in range(presses):     # a terminal's Ctrl-C goes to the whole process group
        os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    line = says_one_line(err)
    assert line.startswith("explorer: interrupted; study 's' keeps its ") and str(journal) in line
    assert "run the same command again to resume" in line
    trials = journal_trials(journal, "s")
    stopped = [t for t in trials if t.system_attrs.get("fail_reason") == "interrupted (Ctrl-C)"]
    assert len(stopped) == 1 and stopped[0].state.name == "FAIL"
    assert [t.user_attrs.get("retry_of") for t in trials].count(stopped[0].number) == 1   # tried again on resume
    assert not list((tmp_path / "s").glob(".*search-lock"))


def test_optuna_says_nothing_of_a_trial_stopped_by_ctrl_c():
    import logging
    quiet = _QuietCtrlC()

    def record(message: str, exc: BaseException | None = None) -> logging.LogRecord:
        info = (type(exc), exc, None) if exc else None
        return logging.LogRecord("optuna.study._optimize", logging.WARNING, __file__, 1, message, None, info)

    assert quiet.filter(record("Trial 3 failed with parameters: {} because of ...", KeyboardInterrupt())) is False
    assert quiet.filter(record("Trial 3 failed with value None.")) is False
    assert quiet.filter(record("Trial 4 failed with parameters: {} because of ...", ValueError("x")))   # a fault
    assert quiet.filter(record("Trial 4 failed with value None."))
