"""The engine knows nothing of the CLI: nothing under src/splatk imports click or rich."""
import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "splatk"


def test_engine_does_not_import_cli_libraries():
    offenders = []
    for py in SRC.rglob("*.py"):
        tree = ast.parse(py.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for n in names:
                if n.split(".")[0] in ("click", "rich", "splatk_cli"):
                    offenders.append(f"{py.relative_to(SRC)}: {n}")
    assert not offenders, offenders
