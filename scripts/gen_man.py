"""Write the man pages in man/ from the click help: ``splatk.1`` and ``splatk-<command>.1``.

Run it after adding or changing any command or option (tests/cli/test_man.py fails until then)::

    pip install click-man
    python scripts/gen_man.py

Pages come from click-man, which walks ``cli.commands`` (every registered, non-hidden command,
sub-groups included), so new commands get a page without touching this script. A page whose
text is unchanged keeps its file (and date); pages of commands that no longer exist are removed.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _body(page: str) -> str:
    """The page without its .TH line (which carries the date)."""
    return "\n".join(line for line in page.splitlines() if not line.startswith(".TH "))


def generate(out_dir: Path) -> list[Path]:
    """(Re)write the pages into ``out_dir``; returns the pages that changed."""
    try:
        from click_man.core import write_man_pages
    except ImportError:
        sys.exit("scripts/gen_man.py needs click-man: pip install click-man")
    from splatk_cli.main import cli

    try:
        ver = version("splatk")
    except PackageNotFoundError:
        ver = "dev"
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        write_man_pages("splatk", cli, version=ver, target_dir=tmp)
        new = {p.name: p.read_text() for p in Path(tmp).glob("*.1")}
    changed = []
    for name, text in sorted(new.items()):
        path = out_dir / name
        if path.is_file() and _body(path.read_text()) == _body(text):
            continue
        path.write_text(text)
        changed.append(path)
    for stale in out_dir.glob("splatk*.1"):
        if stale.name not in new:
            stale.unlink()
            changed.append(stale)
    return changed


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "man", help="folder for the pages (default: man/)")
    args = ap.parse_args(argv)
    changed = generate(args.out)
    print(f"{len(changed)} page(s) changed in {args.out}" + "".join(f"\n  {p.name}" for p in changed))


if __name__ == "__main__":
    main()
