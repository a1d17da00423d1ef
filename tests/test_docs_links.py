"""Every file or folder the documentation points at exists in the repository.

The README, docs/results.md, docs/decisions/ and benchmarks/README.md cite result files, charts,
presets and scripts; a trimmed result folder or a renamed script must not leave a dead
reference behind. Paths are read two ways: repository paths written out (``benchmarks/...``,
``docs/...``, ``presets/...``, ``tests/...``, ``man/...``, ``.ci/...``), and relative markdown
link targets, resolved from the document's own folder. ``{a,b}`` alternatives and ``*`` globs
are expanded; a glob must match at least one file.
"""
from __future__ import annotations

import glob
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "docs" / "results.md", ROOT / "benchmarks" / "README.md",
        *sorted((ROOT / "docs" / "decisions").glob("*.md"))]
TOP_FOLDERS = ("benchmarks", "docs", "presets", "tests", "man", ".ci")

# a path written out from the repository root, not part of a longer path or a word
REPO_PATH = re.compile(r"(?<![\w./~-])(?:\.\./)*(?:%s)/[\w./{},*-]*" % "|".join(re.escape(f) for f in TOP_FOLDERS))
# the target of a markdown link or image: ](target) or ](target#anchor)
LINK_TARGET = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def expand_braces(path: str) -> list[str]:
    m = re.search(r"\{([^{}]*)\}", path)
    if not m:
        return [path]
    return [p for alt in m.group(1).split(",")
            for p in expand_braces(path[:m.start()] + alt + path[m.end():])]


def cited_paths(doc: Path) -> list[tuple[str, Path]]:
    """(as written, resolved path) for every repository path ``doc`` mentions."""
    text = doc.read_text(encoding="utf-8")
    found = []
    for m in REPO_PATH.finditer(text):
        written = m.group(0).rstrip(".,;:")
        base = doc.parent if written.startswith("../") else ROOT
        found += [(written, base / p) for p in expand_braces(written)]
    for m in LINK_TARGET.finditer(text):
        target = m.group(1)
        if "://" in target or target.startswith("mailto:"):
            continue
        found += [(target, doc.parent / p) for p in expand_braces(target)]
    return found


def exists(path: Path) -> bool:
    """Whether ``path`` exists; a glob must match at least one path."""
    path = path.resolve()
    return bool(glob.glob(str(path))) if "*" in str(path) else path.exists()


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_cited_path_exists(doc):
    assert doc.exists(), f"{doc.relative_to(ROOT)} is missing"
    missing = sorted({written for written, path in cited_paths(doc) if not exists(path)})
    assert not missing, f"{doc.relative_to(ROOT)} cites paths that do not exist: {missing}"


def test_the_reader_finds_results_and_decisions_from_the_readme():
    readme = ROOT / "README.md"
    cited = {path.resolve() for _, path in cited_paths(readme)}
    assert (ROOT / "docs" / "results.md").resolve() in cited
    assert (ROOT / "docs" / "decisions").resolve() in cited
    assert len(DOCS) > 4, "docs/decisions/ holds no decision record"


def test_the_checker_reports_a_dead_path(tmp_path):
    doc = tmp_path / "README.md"
    doc.write_text("see `benchmarks/results/no_such_run/x.json` and [it](missing.md)\n"
                   "and `benchmarks/results/real5/charts/psnr_vs_{footprint_mb,nothing}.png`\n"
                   "and `benchmarks/results/real5/results/*.json`, `benchmarks/results/real5/none_*.json`\n")
    missing = [written for written, path in cited_paths(doc) if not exists(path)]
    assert sorted(missing) == ["benchmarks/results/no_such_run/x.json",
                               "benchmarks/results/real5/charts/psnr_vs_{footprint_mb,nothing}.png",
                               "benchmarks/results/real5/none_*.json", "missing.md"]
