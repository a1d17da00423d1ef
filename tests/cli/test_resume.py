"""Crash and resume: a fit killed with SIGKILL, continued with `splatk fit --resume`, stopped again
with Ctrl-C and resumed once more ends where an uninterrupted fit with the same seed ends
(iterations, train log, parameters, test PSNR); checkpoints are written atomically (temp file +
os.replace) and a corrupt one gives a clean error.

The runs are real `splatk` processes on the 32 px demo scene, backend auto (the native one where
it builds), one thread each (the reference run and the run to be killed go side by side). 800
iterations is the shortest run with an MCMC refine step (iteration 600: refine_start 500,
refine_stop 25/30) after the resume, so the density-control generator's restored state is
exercised.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from splatk.models import io as model_io
from splatk_cli.main import cli

ITERS = 800
FIT = ["--iters", str(ITERS), "--checkpoint-every", "200", "--budget", "300", "--init", "random",
       "--seed", "1", "--threads", "1", "--backend", "auto", "--sh-degree", "1", "-q"]


def splatk(*args: str) -> list[str]:
    exe = shutil.which("splatk")
    return ([exe] if exe else [sys.executable, "-m", "splatk_cli.main"]) + [str(a) for a in args]


def log_its(run: Path) -> list[int]:
    path = run / "train_log.jsonl"
    if not path.is_file():
        return []
    its = []
    for line in path.read_text().splitlines():
        try:
            its.append(json.loads(line)["it"])
        except (ValueError, KeyError):
            pass  # a line being written
    return its


def test_atomic_checkpoint_write(tmp_path, monkeypatch):
    """The write goes to a temp file in the same folder, which os.replace moves over the old
    file; a failing write leaves the old file and no temp file."""
    path = tmp_path / "ckpt" / "last.pt"
    model_io.atomic_torch_save({"it": 1}, path)
    replaced = []
    real_replace = os.replace

    def spy(src, dst):
        replaced.append((Path(src), Path(dst)))
        return real_replace(src, dst)

    monkeypatch.setattr(model_io.os, "replace", spy)
    model_io.atomic_torch_save({"it": 2}, path)
    (src, dst), = replaced
    assert dst == path and src.parent == path.parent and src != path and not src.exists()
    assert torch.load(path)["it"] == 2

    def half_write(obj, f, *a, **k):
        f.write(b"PK\x03\x04 cut")
        raise OSError("simulated crash mid-write")

    monkeypatch.setattr(model_io.torch, "save", half_write)
    with pytest.raises(OSError):
        model_io.atomic_torch_save({"it": 3}, path)
    monkeypatch.undo()
    assert torch.load(path)["it"] == 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]


def test_sigkill_then_resume_matches_uninterrupted(tmp_path):
    from splatk.data.synthetic import make_demo_scene

    scene = make_demo_scene(tmp_path / "scene", num_views=9, size=32)
    ref, run = tmp_path / "ref", tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t0 = time.time()
    ref_proc = subprocess.Popen(splatk("fit", scene, "--out", ref, *FIT), env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    proc = subprocess.Popen(splatk("fit", scene, "--out", run, *FIT), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # kill once the log is past a checkpoint (200, 400: checkpoints; 500: log only), so the
        # log holds a line the checkpoint does not cover and resume must drop it
        while not ((run / "checkpoints" / "last.pt").is_file() and max(log_its(run), default=0) >= 500):
            assert proc.poll() is None, f"fit ended before it was killed: {proc.stderr.read()}"
            assert time.time() - t0 < 300, "no checkpoint after 300 s"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    ckpt_it = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["trainer"]["it"]
    assert ckpt_it % 200 == 0 and 200 <= ckpt_it < 600, ckpt_it
    assert not (run / "model.pt").exists()

    # resume, and stop that with one Ctrl-C: it ends at an iteration boundary with a checkpoint
    # there (exit 130); then resume to the end
    proc = subprocess.Popen(splatk("fit", "--resume", "--out", run, "-q"), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while max(log_its(run), default=0) < 700:
            assert proc.poll() is None, f"resumed fit ended early: {proc.stderr.read()}"
            assert time.time() - t0 < 400, "resumed fit too slow"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        err = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "--resume" in err, err
    stop_it = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["trainer"]["it"]
    assert 700 <= stop_it < ITERS, stop_it

    res = subprocess.run(splatk("fit", "--resume", "--out", run, "-q"), env=env, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert ref_proc.wait(timeout=300) == 0, ref_proc.stderr.read()
    ref_proc.stderr.close()
    proc.stderr.close()

    # same end, same log (one line per 100 iterations, none twice, and the same extra lines for
    # events such as MCMC's growth_held), same numbers
    fits = [json.loads((r / "fit.json").read_text()) for r in (ref, run)]
    assert fits[0]["iterations"] == fits[1]["iterations"] == ITERS
    assert log_its(run) == log_its(ref)
    assert [i for i in log_its(run) if i % 100 == 0] == list(range(100, ITERS + 1, 100))
    logs = [[json.loads(ln) for ln in (r / "train_log.jsonl").read_text().splitlines()] for r in (ref, run)]
    for a, b in zip(*logs):
        # torch's CPU kernels are deterministic at one thread; 1e-4 leaves room for a different
        # reduction order, far below what a wrong view order or generator state changes (~1e-2)
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-4), (a, b)
        assert b["num"] == a["num"]
    models = [torch.load(r / "model.pt", weights_only=True)["prims"] for r in (ref, run)]
    for k in models[0]:
        assert torch.allclose(models[0][k], models[1][k], atol=1e-4), k

    psnrs = []
    for r in (ref, run):
        out = CliRunner().invoke(cli, ["eval", str(r), "--json", "--backend", "torch", "--metrics", "psnr"])
        assert out.exit_code == 0, out.output
        psnrs.append(json.loads(out.stdout)["mean"]["psnr"])
    assert abs(psnrs[0] - psnrs[1]) < 0.1, psnrs


def test_resume_errors(tmp_path):
    """--resume without a checkpoint, and with a corrupt one: one clean error line, exit 2."""
    run = tmp_path / "run"
    run.mkdir()
    res = CliRunner().invoke(cli, ["fit", "--resume", "--out", str(run), "-q"])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert res.output.startswith(f"splatk: error: {run}: no checkpoint"), res.output

    (run / "checkpoints").mkdir()
    (run / "config.yaml").write_text("scene: /nowhere\nsettings: {}\n")
    model_io.atomic_torch_save({"trainer": {"it": 1}}, run / "checkpoints" / "last.pt")
    data = (run / "checkpoints" / "last.pt").read_bytes()
    for bad in (data[: len(data) // 2], b"", b"garbage" * 100):
        (run / "checkpoints" / "last.pt").write_bytes(bad)
        res = CliRunner().invoke(cli, ["fit", "--resume", "--out", str(run), "-q"])
        lines = res.output.strip().splitlines()
        assert res.exit_code == 2 and len(lines) == 1 and "Traceback" not in res.output, res.output
        assert lines[0].startswith(f"splatk: error: {run / 'checkpoints' / 'last.pt'}: checkpoint is corrupt")
        assert "without --resume" in lines[0]
        assert (run / "checkpoints" / "last.pt").read_bytes() == bad  # left for the user to inspect
