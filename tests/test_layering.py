"""The layers stay layers (docs/design.md): the engine knows nothing of the CLI, its modules import
each other without a circle, models / kernels / colour models / training see backends only through
the ``splatk.backends`` package API, and modules stay short.

Imports are read with ``ast`` from the source, top-level and function-level alike (a deferred
import inside a function closes a circle just as well, only later)."""
import ast
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "splatk"
CLI = ROOT / "cli"
MAX_LINES = 500


def module_name(py: Path) -> str:
    parts = py.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(py): py for py in SRC.rglob("*.py")}


def imported_names(name: str, py: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in ``py``. ``from P import x`` names the module
    ``P.x`` when that is a module of the package, else ``P``."""
    out = []
    for node in ast.walk(ast.parse(py.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if py.name == "__init__.py" else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            out += [(node.lineno, f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod)
                    for a in node.names]
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the splatk modules it imports."""
    return {n: {m for _, m in imported_names(n, py) if m in MODULES and m != n} for n, py in MODULES.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle as a path that ends where it starts, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(n: str, path: list[str]) -> list[str] | None:
        state[n] = 1
        path.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                return path[path.index(m):] + [m]
            if m not in state and (found := visit(m, path)):
                return found
        path.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n, [])):
            return found
    return None


def test_find_cycle_sees_a_circle_and_its_absence():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_imported_names_resolve_relative_and_function_level_imports():
    names = {m for _, m in imported_names("splatk.models.volumetric", MODULES["splatk.models.volumetric"])}
    assert {"splatk.backends", "splatk.kernels", "splatk.models.base"} <= names
    export = {m for _, m in imported_names("splatk.stages.export", MODULES["splatk.stages.export"])}
    assert "splatk.render_path" in export  # imported inside export_renders


def test_no_import_circle():
    assert find_cycle(import_graph()) is None


def test_engine_does_not_import_cli_libraries():
    offenders = [f"{py.relative_to(SRC)}:{line}: {m}" for n, py in MODULES.items()
                 for line, m in imported_names(n, py) if m.split(".")[0] in ("click", "rich", "splatk_cli")]
    assert not offenders, offenders


def test_models_kernels_colors_train_see_backends_only_through_the_package():
    """They take a backend object (``splatk.backends.get``) and the contract's types from the
    package; no backend module by name, so a new backend changes none of them."""
    offenders = []
    for n, py in MODULES.items():
        if n.split(".")[1:2] not in (["models"], ["image"], ["kernels"], ["colors"], ["train"]):
            continue
        offenders += [f"{py.relative_to(SRC)}:{line}: {m}" for line, m in imported_names(n, py)
                      if m.startswith("splatk.backends.")]
    assert not offenders, offenders


def _long_modules() -> dict[str, int]:
    files = [*SRC.rglob("*.py"), *CLI.rglob("*.py")]
    counts = {str(py.relative_to(SRC if SRC in py.parents else ROOT)): len(py.read_text().splitlines())
              for py in files}
    return {name: n for name, n in counts.items() if n > MAX_LINES}


def test_no_module_over_500_lines():
    assert not _long_modules(), _long_modules()


def test_every_package_ships_in_the_wheel():
    """pyproject.toml lists packages explicitly: a new package folder must be listed, or a wheel
    install lacks it."""
    import tomllib

    listed = set(tomllib.loads((SRC.parents[1] / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(SRC.parent).parts) for p in SRC.rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)
