"""Progress where stderr is not a terminal (a log file, a batch job, CI): plain lines every
--log-every seconds, with iteration/total, loss, PSNR, primitives, it/s and ETA, and no escapes."""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys

import cv2
import numpy as np
from click.testing import CliRunner
from rich.console import Console
from rich.progress import Progress

from splatk.data.synthetic import make_demo_scene
from splatk_cli.main import cli
from splatk_cli.progress import PlainProgress, training_progress

FIT_LINE = re.compile(r"^fit (\d+)/(\d+) \(\d+%\)  loss \d+\.\d{4}  PSNR -?\d+\.\d\d  [\d,]+ prims  "
                      r"\d+\.\d it/s  elapsed \d+:\d\d:\d\d  ETA (\d+:\d\d:\d\d|\?)$")


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_plain_lines_follow_the_clock():
    out, clock = io.StringIO(), FakeClock()
    progress = PlainProgress(Console(file=out), "loss {loss:.4f}  PSNR {psnr:.2f}  {num:,} prims", every=10, clock=clock)
    task = progress.add_task("fit", total=1000, completed=0, loss=0.0, psnr=0.0, num=100)
    for it in range(10, 1001, 10):  # one update per second
        clock.now += 1.0
        progress.update(task, completed=it, loss=1.0 / it, psnr=it / 50, num=100 + it)
    progress.stop()
    progress.stop()  # idempotent: the fit command stops it on every way out
    lines = out.getvalue().splitlines()
    assert len(lines) == 10, lines  # every 10 s of 100 s
    assert lines[0] == ("fit 100/1000 (10%)  loss 0.0100  PSNR 2.00  200 prims  10.0 it/s  "
                        "elapsed 0:00:10  ETA 0:01:30")
    assert lines[-1].startswith("fit 1000/1000 (100%)") and lines[-1].endswith("ETA 0:00:00")


def test_the_last_state_is_printed_at_stop():
    out, clock = io.StringIO(), FakeClock()
    progress = PlainProgress(Console(file=out), "loss {loss:.4f}", every=10, clock=clock)
    task = progress.add_task("fit", total=50, completed=20, loss=0.5)  # a resumed run
    clock.now = 3.0
    progress.update(task, completed=50, loss=0.25)
    assert out.getvalue() == ""
    progress.stop()
    # the rate counts this process's 30 iterations, not the 20 before the resume
    assert out.getvalue() == "fit 50/50 (100%)  loss 0.2500  10.0 it/s  elapsed 0:00:03  ETA 0:00:00\n"


def test_a_terminal_gets_the_bar():
    assert isinstance(training_progress(Console(file=io.StringIO(), force_terminal=True)), Progress)
    assert isinstance(training_progress(Console(file=io.StringIO())), PlainProgress)


def test_fit_logs_plain_progress_lines_to_a_pipe(tmp_path):
    scene = make_demo_scene(tmp_path / "scene", num_views=8, size=32)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TERM": "xterm-256color"}
    env.pop("FORCE_COLOR", None)
    cmd = [sys.executable, "-m", "splatk_cli.main", "fit", str(scene), "--out", str(tmp_path / "run"),
           "--iters", "300", "--budget", "300", "--init", "random", "--sh-degree", "1", "--backend", "torch",
           "--threads", "1", "--log-every", "0.2"]
    res = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "\x1b" not in res.stderr, "escape sequences in a log"
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("fit ")]
    matches = [FIT_LINE.match(ln) for ln in lines]
    assert lines and all(matches), lines
    its = [int(m.group(1)) for m in matches]
    assert len(its) >= 2 and its == sorted(its) and its[-1] == 300, its
    assert all(int(m.group(2)) == 300 for m in matches)
    assert any(m.group(3) != "?" for m in matches[:-1]), "no ETA while running"
    assert (tmp_path / "run" / "model.pt").is_file()
    # messages stay one line each in a log (rich wraps at 80 columns unless told otherwise)
    (start,) = [ln for ln in res.stderr.splitlines() if ln.startswith("splatk fit ")]
    assert start.endswith("kernel gaussian, backend torch"), start


def test_image_logs_plain_progress_lines(tmp_path):
    photo = tmp_path / "p.png"
    cv2.imwrite(str(photo), (np.random.default_rng(0).random((32, 48, 3)) * 255).astype(np.uint8))
    res = CliRunner().invoke(cli, ["image", str(photo), "--iters", "20", "--no-lpips", "--kernel", "gaussian",
                                   "--budget-bytes", "2KB", "--threads", "1", "--backend", "torch",
                                   "--log-every", "0", "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("image ")]
    assert lines and "\x1b" not in res.stderr
    assert all(re.match(r"^image \d+/20 \(\d+%\)  loss \d+\.\d{5}  PSNR -?\d+\.\d\d  \d+\.\d it/s  "
                        r"elapsed \d+:\d\d:\d\d  ETA (\d+:\d\d:\d\d|\?)$", ln) for ln in lines), lines
    assert lines[-1].startswith("image 20/20")


def test_pretrain_logs_plain_progress_lines(tmp_path):
    res = CliRunner().invoke(cli, ["pretrain", "--kind", "planar", "--out", str(tmp_path / "k.pt"), "--steps", "20",
                                   "--log-every", "0"])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("pretrain ")]
    assert lines and "\x1b" not in res.stderr
    assert all(re.match(r"^pretrain \d+/\d+ \(\d+%\)  surfel  loss \d+\.\d{4}  \d+\.\d it/s  "
                        r"elapsed \d+:\d\d:\d\d  ETA (\d+:\d\d:\d\d|\?)$", ln) for ln in lines), lines
    total = lines[-1].split()[1].split("/")[1]
    assert lines[-1].startswith(f"pretrain {total}/{total} (100%)")
