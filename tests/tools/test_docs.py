"""Every public name of the package is documented in the Sphinx sources (docs/), so a new export without a doc fails.

Cheap by design: the reST sources are read as text, no Sphinx build (``make docs`` builds and runs the examples).
A name counts as documented when an ``auto*`` or ``py:*`` directive names it, either in full or under the module set by
the last ``.. module::`` / ``.. currentmodule::`` / ``.. automodule::`` of its page, or in the explicit ``:members:``
list of an ``automodule``.
"""

import ast
import importlib
import importlib.util
import re
import runpy
import sys
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from stable_baselines3.common.base_class import BaseAlgorithm

import sb3_dipper
from tests.conftest import ALL_ALGORITHMS, any_tiny_model

DOCS = Path(__file__).resolve().parents[2] / "docs"
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


# ---------------------------------------------------------------------------------------------------- `make docs`

ROOT = DOCS.parent


def setup_requirements() -> tuple[list[str], dict[str, list[str]]]:
    """``install_requires`` and ``extras_require`` of setup.py, read from its source (running it would call setup())."""
    call = next(
        node
        for node in ast.walk(ast.parse((ROOT / "setup.py").read_text(encoding="utf-8")))
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "setup"
    )
    keywords = {keyword.arg: keyword.value for keyword in call.keywords}
    return ast.literal_eval(keywords["install_requires"]), ast.literal_eval(keywords["extras_require"])


def make_docs_extras() -> list[str]:
    """The extras the Makefile's docs target installs (``pip install -e ".[zoo,plots,docs]"``)."""
    recipe = (ROOT / "Makefile").read_text(encoding="utf-8").split("$(DOCS_STAMP): ", 1)[1]
    match = re.search(r'pip install .*-e "\.\[([\w,]+)\]"', recipe)
    assert match, "the Makefile's docs target installs no extras of the package"
    return match.group(1).split(",")


def installed_with(requirements: list[str]) -> set[str]:
    """The distributions that installing ``requirements`` brings, their dependencies included (as installed here)."""
    installed: set[str] = set()
    pending = [Requirement(requirement) for requirement in requirements]
    while pending:
        requirement = pending.pop()
        name = canonicalize_name(requirement.name)
        if name in installed:
            continue
        installed.add(name)
        try:
            dependencies = metadata.requires(requirement.name) or []
        except metadata.PackageNotFoundError:  # not installed here: its dependencies are unknown
            continue
        for dependency in map(Requirement, dependencies):
            wanted = ["", *requirement.extras]
            if dependency.marker is None or any(dependency.marker.evaluate({"extra": extra}) for extra in wanted):
                pending.append(dependency)
    return installed


def module_level_imports(path: Path) -> set[str]:
    """The top-level packages a module imports when it is imported (imports inside functions wait for a call)."""
    names = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Import):
            names |= {alias.name.partition(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.partition(".")[0])
    return names - set(sys.stdlib_module_names) - {"sb3_dipper"}


def test_make_docs_installs_what_autodoc_imports():
    # The API pages import every module of the package; -W turns a failed import into a failed build.
    install_requires, extras = setup_requirements()
    installed = installed_with([*install_requires, *(req for extra in make_docs_extras() for req in extras[extra])])
    distributions = metadata.packages_distributions()
    missing = {
        f"{path.relative_to(ROOT)} imports {package}"
        for path in sorted((ROOT / "sb3_dipper").rglob("*.py"))
        for package in module_level_imports(path)
        if not {canonicalize_name(name) for name in distributions.get(package, [package])} & installed
    }
    assert not missing, f"`make docs` lacks what autodoc imports: {sorted(missing)}; add it to setup.py's docs extra"


def test_math_is_rendered_by_a_mathjax_copied_into_the_site(tmp_path):
    pytest.importorskip("sphinx")
    from sphinx.application import Sphinx

    conf = runpy.run_path(str(DOCS / "conf.py"))
    math_extensions = [name for name in conf["extensions"] if "math" in name]
    source = tmp_path / "source"
    source.mkdir()
    (source / "conf.py").write_text(f"extensions = {math_extensions!r}\n")
    (source / "index.rst").write_text("Math\n====\n\n:math:`\\pi^H(u \\mid s, g)`\n")
    Sphinx(str(source), str(source), str(tmp_path / "html"), str(tmp_path / "doctrees"), "html", status=None).build()
    scripts = re.findall(r'<script[^>]*src="([^"]*mathjax[^"]*)"', (tmp_path / "html" / "index.html").read_text())
    assert scripts, "the page loads no MathJax: its math would show as raw LaTeX"
    # Relative and inside the site: the page renders its math with no network (no CDN at build or view time).
    assert all("://" not in script and (tmp_path / "html" / script).is_file() for script in scripts), scripts


# ---------------------------------------------------------------------------------------------------- algorithm pages


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS, ids=lambda model_class: model_class.__name__)
def test_an_algorithm_page_says_whether_predict_carries_a_recurrent_state(model_class, maze_env):
    page = (DOCS / "modules" / f"{model_class.__module__.split('.')[1]}.rst").read_text(encoding="utf-8")
    model = any_tiny_model(model_class, maze_env)
    _, state = model.predict(maze_env.reset())
    # "Recurrent policies: no" beside "predict takes a recurrent state" read as a contradiction: the page names both.
    assert "Recurrent policy networks (LSTM): ❌" in page or "Recurrent policies: ❌" in page
    assert ("``predict``'s recurrent ``state``: ✔️" in page) == (state is not None)
    assert "Recurrent policies: ❌ (" not in page


# ---------------------------------------------------------------------------------------------------- torch threads


def zoo_train_num_threads_default() -> str:
    """``--num-threads`` of ``sb3-dipper-zoo train``: a value our runner adds, else rl-zoo3's train default."""
    from sb3_dipper.zoo import zoo_argv

    argv = zoo_argv("train", ["--algo", "dipper", "--env", "PointMazeFourRooms-v0"])
    if "--num-threads" in argv:
        return argv[argv.index("--num-threads") + 1]
    source = Path(importlib.util.find_spec("rl_zoo3.train").origin).read_text(encoding="utf-8")
    match = re.search(r'"--num-threads".*?default=(-?\d+)', source)
    assert match, "rl-zoo3's train has no --num-threads default to read"
    return match.group(1)


def test_the_readme_and_the_zoo_page_say_how_to_train_with_one_thread():
    page = (DOCS / "guide" / "zoo.rst").read_text(encoding="utf-8")
    assert f"``--num-threads`` defaults to ``{zoo_train_num_threads_default()}``" in page
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert f"its default, `{zoo_train_num_threads_default()}`," in readme
    for text in (page, readme):
        assert "--num-threads 1" in text and "torch.set_num_threads(1)" in text
