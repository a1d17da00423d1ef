"""The fields of RUN/train_log.jsonl are the ones the README and `splatk fit`'s man page list."""
from __future__ import annotations

import json
import re
from pathlib import Path

from splatk.data.synthetic import make_demo_scene
from splatk.stages.fit import FitConfig, run_fit
from splatk.train.trainer import TrainConfig

ROOT = Path(__file__).resolve().parents[2]


def _documented(text: str, opening: str) -> set[str]:
    """The field names a paragraph starting with ``opening`` lists: `name` (README) or name (man)
    followed by a parenthesised meaning."""
    start = text.index(opening)
    paragraph = text[start:text.index("\n.SH" if text.startswith(".TH") else "\nOn a terminal", start)]
    return set(re.findall(r"`?(\w+)`?\s+\(", paragraph)) - {"message"}


def test_the_documented_fields_are_the_logged_ones(tmp_path):
    scene = make_demo_scene(tmp_path / "scene", num_views=4, size=16)
    cfg = FitConfig(sh_degree=0, backend="torch", threads=1,
                    train=TrainConfig(iters=100, budget=50, init="random", backend="torch"))
    run = run_fit(scene, tmp_path / "run", cfg).path
    lines = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert lines and lines[-1]["it"] == 100
    logged = set(lines[-1])
    readme = _documented((ROOT / "README.md").read_text(), "`train_log.jsonl` has a JSON line")
    man = _documented((ROOT / "man" / "splatk-fit.1").read_text(), "RUN/train_log.jsonl gets a JSON line")
    assert readme == logged, f"README lists {sorted(readme)}, train_log.jsonl has {sorted(logged)}"
    assert man == logged, f"man/splatk-fit.1 lists {sorted(man)}, train_log.jsonl has {sorted(logged)}"
