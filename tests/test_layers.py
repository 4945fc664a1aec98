"""The package's layering: ``sb3_dipper/common/`` is the ground floor, importing nothing from ``envs/`` or an algorithm
folder, so that every algorithm and every task can build on it (tasks plug in through its registries)."""

import ast
from pathlib import Path

import sb3_dipper

COMMON = Path(sb3_dipper.__file__).parent / "common"


def package_imports(module: Path) -> set[str]:
    """The ``sb3_dipper`` modules a file imports, at module level or inside functions."""
    imported = set()
    for node in ast.walk(ast.parse(module.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            imported.add(node.module)
        elif isinstance(node, ast.Import):
            imported.update(alias.name for alias in node.names)
    return {name for name in imported if name == "sb3_dipper" or name.startswith("sb3_dipper.")}


def test_common_imports_only_common():
    modules = sorted(COMMON.glob("*.py"))
    assert len(modules) > 10
    outside = {
        module.name: sorted(name for name in package_imports(module) if not name.startswith("sb3_dipper.common"))
        for module in modules
    }
    assert {name: imports for name, imports in outside.items() if imports} == {}


def test_the_check_sees_an_import_from_a_task(tmp_path):
    module = tmp_path / "module.py"
    module.write_text("def f():\n    from sb3_dipper.envs.demos import default_demonstrations\n")
    assert package_imports(module) == {"sb3_dipper.envs.demos"}
