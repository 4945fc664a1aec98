"""Every public name of the package is documented in the Sphinx sources (docs/), so a new export without a doc fails.

Cheap by design: the reST sources are read as text, no Sphinx build (``make docs`` builds and runs the examples).
A name counts as documented when an ``auto*`` or ``py:*`` directive names it, either in full or under the module set by
the last ``.. module::`` / ``.. currentmodule::`` / ``.. automodule::`` of its page, or in the explicit ``:members:``
list of an ``automodule``.
"""

import importlib
import re
from pathlib import Path

import pytest
from stable_baselines3.common.base_class import BaseAlgorithm

import sb3_dipper

DOCS = Path(__file__).resolve().parent.parent / "docs"
MODULE_DIRECTIVE = re.compile(r"^\.\. (?:py:)?(?:module|currentmodule|automodule):: +(\S+)\s*$")
OBJECT_DIRECTIVE = re.compile(r"^\.\. (?:auto|py:)(?:class|function|data|exception|attribute|method):: +([\w.]+)")
MEMBERS_OPTION = re.compile(r"^ +:members: +(\S.*)$")


def documented_names(docs: Path | None = None) -> set[str]:
    """Full dotted names of the objects the reST sources under ``docs`` (default: the repository's) document."""
    names: set[str] = set()
    for page in sorted((docs or DOCS).rglob("*.rst")):
        if "_build" in page.parts:
            continue
        module = ""
        last_automodule = ""
        for line in page.read_text(encoding="utf-8").splitlines():
            if match := MODULE_DIRECTIVE.match(line):
                module = match.group(1)
                last_automodule = module if line.startswith(".. automodule::") else ""
            elif match := OBJECT_DIRECTIVE.match(line):
                name = match.group(1)
                names.add(name if name.startswith("sb3_dipper.") or not module else f"{module}.{name}")
                last_automodule = ""
            elif (match := MEMBERS_OPTION.match(line)) and last_automodule:
                names.update(f"{last_automodule}.{member.strip()}" for member in match.group(1).split(","))
    return names


def algorithm_packages() -> list[str]:
    """The packages of the algorithms ``sb3_dipper`` exports (``sb3_dipper.dipper``, ...), the envs and the labelling
    package."""
    packages = {
        getattr(sb3_dipper, name).__module__.rsplit(".", 1)[0]
        for name in sb3_dipper.__all__
        if isinstance(getattr(sb3_dipper, name), type) and issubclass(getattr(sb3_dipper, name), BaseAlgorithm)
    }
    return [*sorted(packages), "sb3_dipper.envs", "sb3_dipper.labelling"]


def resolve(dotted_name: str) -> object:
    module_name, _, attribute = dotted_name.rpartition(".")
    try:
        return getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError):
        return None


def test_the_parser_reads_directives_under_their_module(tmp_path):
    (tmp_path / "page.rst").write_text(
        ".. module:: sb3_dipper.dipper\n\n.. autoclass:: DIPPER\n   :members:\n\n"
        ".. autofunction:: sb3_dipper.register_subgoal_space\n\n"
        ".. automodule:: sb3_dipper.raps.primitives\n   :members: PrimitiveSpace, Reach\n"
    )
    assert documented_names(tmp_path) == {
        "sb3_dipper.dipper.DIPPER",
        "sb3_dipper.register_subgoal_space",
        "sb3_dipper.raps.primitives.PrimitiveSpace",
        "sb3_dipper.raps.primitives.Reach",
    }


def test_every_algorithm_package_is_checked():
    assert {"sb3_dipper.dipper", "sb3_dipper.hier", "sb3_dipper.dpo_flat", "sb3_dipper.dac"} <= set(algorithm_packages())


def test_every_top_level_export_is_documented():
    documented = documented_names()
    documented_objects = [resolve(name) for name in documented]
    missing = [
        name
        for name in sb3_dipper.__all__
        if f"sb3_dipper.{name}" not in documented and not any(obj is getattr(sb3_dipper, name) for obj in documented_objects)
    ]
    assert not missing, (
        f"sb3_dipper exports {missing} but no page in docs/ documents them: add an `.. autoclass::` (or "
        "`.. autofunction::`) to the algorithm's page in docs/modules/ or to docs/api/sb3_dipper.rst"
    )


@pytest.mark.parametrize("package", algorithm_packages())
def test_every_export_of_a_package_is_documented(package):
    exports = importlib.import_module(package).__all__
    documented = documented_names()
    missing = [name for name in exports if f"{package}.{name}" not in documented]
    assert not missing, (
        f"{package} exports {missing} but no page in docs/ documents them: add `.. autoclass:: <name>` (or "
        f"`.. autofunction::`, `.. py:data::`) under `.. module:: {package}` on its page in docs/modules/ or docs/api/"
    )
