"""The code's layout rules: product code does not import study code; tests do not import each other."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, names) of every import statement in a file, nested ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            found.append((node.module, [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            found.extend((alias.name, []) for alias in node.names)
    return found


def _product_files():
    for path in sorted((ROOT / "ivc").rglob("*.py")):
        parts = path.relative_to(ROOT).parts
        if "studies" not in parts and parts[1] != "cli":
            yield path


def test_product_code_does_not_import_study_code():
    offenders = [f"{path.relative_to(ROOT)}: {module}" for path in _product_files()
                 for module, names in _imports(path)
                 if module.startswith("ivc.predict.studies") or (module == "ivc.predict" and "studies" in names)]
    assert not offenders, offenders


def test_no_test_module_imports_another():
    offenders = [f"{path.name}: {module}" for path in sorted((ROOT / "tests").glob("test_*.py"))
                 for module, _ in _imports(path) if module.startswith("tests.test_")]
    assert not offenders, offenders


def test_no_test_imports_a_private_name():
    offenders = [f"{path.name}: {module}.{name}" for path in sorted((ROOT / "tests").glob("*.py"))
                 for module, names in _imports(path) if module.startswith("ivc")
                 for name in names if name.startswith("_") and not name.startswith("__")]
    assert not offenders, offenders


def test_no_product_module_imports_another_modules_private_name():
    offenders = [f"{path.relative_to(ROOT)}: {module}.{name}" for path in _product_files()
                 for module, names in _imports(path) if module.startswith("ivc")
                 for name in names if name.startswith("_") and not name.startswith("__")]
    assert not offenders, offenders
