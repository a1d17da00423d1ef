"""The files of a fit's run folder while it trains, written by one object.

Layout::

    RUN/config.yaml          resolved settings, with where each value came from
    RUN/checkpoints/last.pt  full training state, written atomically every N iterations
    RUN/model.pt             final model (native format; `splatk export` converts it)
    RUN/fit.json             summary: iterations, wall time, primitives, events (NaN rollbacks),
                             test PSNR of the initial model, the auto-budget report
    RUN/train_log.jsonl      loss / PSNR / primitive count (planar geometry terms) every 100 iterations
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import yaml

from ..errors import InputError
from ..models.io import atomic_torch_save, save_model


def write_config(out: Path, scene_path, settings: dict, sources: dict) -> None:
    """RUN/config.yaml: the scene, every setting (``FitConfig.to_dict()``) and where each came from."""
    doc = {"scene": str(Path(scene_path).resolve()), "settings": settings, "sources": sources}
    (out / "config.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


def record_resume_changes(out: Path, settings: dict, changes: dict, it: int) -> None:
    """config.yaml takes the settings a resume changed, and says so beside each."""
    path = out / "config.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["settings"] = settings
    for key, value in changes.items():
        doc.setdefault("sources", {})[key.split(".")[-1]] = f"changed on resume at iteration {it}: {value}"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def clean_resume_leftovers(out: Path, it: int) -> None:
    """Before continuing at iteration ``it``: drop temp files of a write that was killed and the
    log lines written after the checkpoint (they are about to be written again)."""
    for tmp in (out / "checkpoints").glob("*.tmp"):
        tmp.unlink(missing_ok=True)
    for tmp in out.glob("model.pt.*.tmp"):
        tmp.unlink(missing_ok=True)
    log = out / "train_log.jsonl"
    if log.is_file():
        keep = []
        for line in log.read_text().splitlines():
            try:
                if json.loads(line)["it"] <= it:
                    keep.append(line)
            except (ValueError, KeyError, TypeError):
                continue  # a line cut off by the kill
        log.write_text("".join(x + "\n" for x in keep))


class RunFolder:
    """Checkpoints, the training log, the model and the summary of one run folder.

    ``spec`` and ``meta`` (``models.io``) go into every checkpoint and the model file;
    ``saved_it`` is the iteration of the checkpoint on disk (None: none yet), which an error
    message about a failed write names as the state that survives.
    """

    def __init__(self, out: Path, spec: dict, meta: dict, saved_it: int | None = None):
        self.out = Path(out)
        self.spec, self.meta = spec, meta
        self.saved_it = saved_it
        self.checkpoint_path = self.out / "checkpoints" / "last.pt"
        self._log = open(self.out / "train_log.jsonl", "a")

    def checkpoint(self, it: int, state: dict) -> None:
        """Write ``state`` (with spec and meta) as the checkpoint of iteration ``it``."""
        state = {**state, "spec": self.spec, "meta": self.meta}
        self._save(lambda: atomic_torch_save(state, self.checkpoint_path), self.checkpoint_path)
        self.saved_it = it

    def log_step(self, info) -> None:
        """A line of train_log.jsonl every 100 iterations and at every event."""
        if info.it % 100 == 0 or info.event:
            self._log.write(json.dumps({"it": info.it, "loss": info.loss, "psnr": info.psnr,
                                        "num": info.num_primitives, "elapsed": round(info.elapsed, 3),
                                        "event": info.event, "normal_loss": info.normal_loss,
                                        "distortion_loss": info.distortion_loss}) + "\n")
            self._log.flush()

    def close_log(self) -> None:
        self._log.close()

    def save_model(self, model, train_cameras: list | None = None) -> None:
        """model.pt, with the cameras it was fitted to (decision 0121's hold reads them)."""
        path = self.out / "model.pt"
        self._save(lambda: save_model(model, path, self.spec, self.meta, train_cameras), path)

    def write_summary(self, summary: dict) -> None:
        (self.out / "fit.json").write_text(json.dumps(summary, indent=2))

    def _save(self, write: Callable[[], object], path: Path) -> None:
        """Run an atomic write; a full disk or a permission problem becomes an InputError.

        The atomic write leaves the previous file in place, so the message can say what survives.
        """
        try:
            write()
        except OSError as e:
            kept = (f"the checkpoint of iteration {self.saved_it} is intact; " if self.saved_it is not None else "")
            raise InputError(path, f"cannot write ({e.strerror or e})",
                             f"free disk space or fix permissions; {kept}continue with `splatk fit --resume "
                             f"--out {self.out}`") from None
