"""The package's shape: no private names imported across modules, first lines that say what a module is, every package installed."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "polins"
MODULES = sorted(PACKAGE.rglob("*.py"))


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _private_imports(source: str, own: str) -> list[str]:
    """``from polins.x import _name`` (or ``import polins.x._y``) where x is not ``own``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("polins"):
            if node.module == own:
                continue
            found += [
                f"{node.module}.{a.name} (line {node.lineno})"
                for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")
            ]
            if any(p.startswith("_") and not p.startswith("__") for p in node.module.split(".")):
                found.append(f"{node.module} (line {node.lineno})")
        elif isinstance(node, ast.Import):
            found += [
                f"{a.name} (line {node.lineno})"
                for a in node.names
                if a.name.startswith("polins")
                and any(p.startswith("_") and not p.startswith("__") for p in a.name.split("."))
            ]
    return found


def test_the_package_has_modules():
    assert len(MODULES) > 30
    assert {_module_name(p) for p in MODULES} >= {"polins", "polins.site", "polins.fusion.config"}


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE.parent)))
def test_no_private_names_imported_across_modules(path):
    assert _private_imports(path.read_text(), _module_name(path)) == []


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE.parent)))
def test_module_first_line_says_what_it_is(path):
    doc = ast.get_docstring(ast.parse(path.read_text()))
    assert doc, f"{path.name}: the first line must say what the module is"
    assert len(doc.splitlines()[0]) >= 20


def test_the_private_import_check_catches_one():
    source = (
        "from polins.frames import _x, y\nfrom polins.fusion import _own\nimport polins._hidden\n"
    )
    assert _private_imports(source, "polins.fusion") == [
        "polins.frames._x (line 1)",
        "polins._hidden (line 3)",
    ]


def test_every_package_is_installed():
    """Every folder of polins/ with an ``__init__.py`` is listed in pyproject's packages."""
    import tomllib

    pyproject = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())
    listed = set(pyproject["tool"]["setuptools"]["packages"])
    found = {_module_name(p) for p in PACKAGE.rglob("__init__.py")}
    assert found - listed == set()


def test_shipped_models_load_from_a_source_checkout(tmp_path):
    """``polins`` imported from the checkout itself (not an installed copy) finds the shipped
    model files in the top-level ``models/`` folder."""
    import os
    import subprocess
    import sys

    code = (
        "import polins; from polins.models.schema import shipped_folder; "
        f"assert polins.__file__.startswith({str(PACKAGE)!r}), polins.__file__; "
        "print(shipped_folder('cameras')); print(polins.load_camera('paper-table1').name)"
    )
    env = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    folder, name = out.stdout.split()
    assert name == "paper-table1"
    assert Path(folder) == PACKAGE.parent / "models" / "cameras"
