"""SIGTERM (a scheduler's or `timeout`'s stop) saves the checkpoint and exits 128 + 15, so the
caller sees that the run did not finish; `--resume` continues it."""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time

import torch

from splatk.data.synthetic import make_demo_scene


def splatk(*args) -> list[str]:
    exe = shutil.which("splatk")
    return ([exe] if exe else [sys.executable, "-m", "splatk_cli.main"]) + [str(a) for a in args]


def test_sigterm_saves_and_exits_143(tmp_path):
    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    out = tmp_path / "run"
    proc = subprocess.Popen(splatk("fit", scene, "--out", out, "--iters", "100000", "--budget", "100",
                                   "--backend", "torch", "--threads", "1", "-q"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out / "train_log.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (log.is_file() and log.read_text().count("\n") >= 2):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "SIGTERM" in err and "--resume" in err
    it = torch.load(out / "checkpoints" / "last.pt", weights_only=True)["trainer"]["it"]
    assert it >= 100
    res = subprocess.run(splatk("fit", "--resume", "--out", out, "--iters", str(it + 10), "-q"),
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "fit.json").read_text())["iterations"] == it + 10


def test_sigterm_stops_bench_with_the_checkpoint_and_no_result(tmp_path):
    """`bench` under SIGTERM stops the fit in progress as `fit` does (no stack dump from
    pycolmap's handler, which replaces Python's when imported later), writes no result for the
    unfinished run, and exits 143."""
    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    out = tmp_path / "bench"
    proc = subprocess.Popen(splatk("bench", scene, "--out", out, "--kernel", "gaussian", "--budget", "100",
                                   "--iters", "100000", "--backend", "torch", "--threads", "1", "--metrics", "psnr"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    logs = []
    while time.time() < deadline and not (logs and logs[0].read_text().count("\n") >= 2):
        time.sleep(0.2)
        logs = list(out.glob("runs/*/*/train_log.jsonl"))
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "stopped by SIGTERM" in err and "Aborted" not in err and "Traceback" not in err, err
    assert (logs[0].parent / "checkpoints" / "last.pt").is_file()
    assert not list(out.glob("results/*.json"))


def test_sigterm_ends_a_command_without_stop_logic_in_one_line(tmp_path):
    """A command that does not checkpoint (here `pretrain`) ends on SIGTERM with exit 143 and one
    line, not pycolmap's stack dump, and leaves no weights file behind."""
    out = tmp_path / "weights.pt"
    proc = subprocess.Popen(splatk("pretrain", "--steps", "10000000", "--out", out),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stderr.readline()  # the first progress line: the command is running
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "stopped by SIGTERM" in err and "Aborted" not in err and "Traceback" not in err, err
    assert not out.exists()
