"""Every third-party package the code imports is declared where an install of that code gets it.

`shared` is in every install, so its imports must be in `[project] dependencies`; `field`
gets those plus the `field` extra, `postproc` those plus the `post` extra. Imports are read
from the source (every `import`, also the ones inside functions), and each imported module
is mapped to the distributions that provide it in this environment.
"""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from collections.abc import Mapping
from functools import cache
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Each installable package and the extras that an install using it brings (beside the base
# dependencies): `sim` serves `wreckmap-field sim` (and the tests and benches).
INSTALLS = {"shared": (), "sim": ("field",), "field": ("field",), "postproc": ("post",)}

# Imported by bench/ only when present, and deliberately not a dependency.
OPTIONAL_TOOLS = {"atheris": "tests/fuzz/campaign.py --atheris: no wheel installs on Python 3.11"}


def canonical(name: str) -> str:
    """A distribution name as packaging compares them (PEP 503): `PyYAML` -> `pyyaml`."""
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_name(requirement: str) -> str:
    """`"numpy==2.4.6"` -> `"numpy"` (also with extras, markers or other operators)."""
    match = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
    assert match, f"pyproject.toml: unreadable requirement {requirement!r}"
    return canonical(match.group(1))


@cache
def project() -> dict[str, object]:
    table = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert isinstance(table, dict)
    return table


def declared(*extras: str) -> set[str]:
    """Distribution names an install with these extras asks for directly."""
    table = project()
    requirements = list(table["dependencies"])  # type: ignore[call-overload]
    optional = table["optional-dependencies"]
    assert isinstance(optional, dict)
    for extra in extras:
        requirements += optional[extra]
    return {requirement_name(requirement) for requirement in requirements}


def local_modules(folder: Path) -> set[str]:
    """Module names a test or bench imports from its own folder (helpers put on sys.path)."""
    return {path.stem for path in folder.rglob("*.py")} | {
        path.name for path in folder.rglob("*") if path.is_dir()
    }


def imported_modules(folder: Path) -> dict[str, set[str]]:
    """Top-level third-party module -> the files under `folder` that import it."""
    found: dict[str, set[str]] = {}
    local = local_modules(folder)
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                root = name.split(".")[0]
                first_party = (REPO / root).is_dir()
                if root in sys.stdlib_module_names or first_party or root in local:
                    continue
                found.setdefault(root, set()).add(str(path.relative_to(folder.parent)))
    return found


@cache
def installed_providers() -> Mapping[str, list[str]]:
    return metadata.packages_distributions()


def providers(module: str) -> set[str]:
    """Distributions installed here that provide the top-level `module`."""
    return {canonical(name) for name in installed_providers().get(module, [])}


def undeclared(modules: dict[str, set[str]], allowed: set[str]) -> list[str]:
    problems = []
    for module, files in sorted(modules.items()):
        dists = providers(module)
        if not dists:
            problems.append(f"{module} (imported by {sorted(files)}): not installed here")
        elif not dists & allowed:
            problems.append(f"{module} from {sorted(dists)} (imported by {sorted(files)})")
    return problems


def test_every_installed_package_has_its_extras_named() -> None:
    """A new top-level package in the wheel needs a line in INSTALLS (which extra serves it)."""
    find = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"][
        "setuptools"
    ]["packages"]["find"]
    packages = {pattern.rstrip("*") for pattern in find["include"]}
    assert packages == set(INSTALLS)


@pytest.mark.parametrize("package", sorted(INSTALLS))
def test_imports_are_declared_for_the_install(package: str) -> None:
    extras = INSTALLS[package]
    modules = imported_modules(REPO / package)
    assert modules, f"{package}/: no third-party import found (is the folder there?)"
    problems = undeclared(modules, declared(*extras))
    where = "[project] dependencies" + "".join(f" or the {extra!r} extra" for extra in extras)
    assert not problems, f"{package}/ imports packages missing from {where}: {problems}"


def setup_extras() -> tuple[str, ...]:
    """The extras deploy/setup.sh (what `make setup` runs) installs: `-e ".[a,b]"`."""
    text = (REPO / "deploy" / "setup.sh").read_text(encoding="utf-8")
    match = re.search(r'pip install[^\n]*-e "\.\[([\w,-]+)\]"', text)
    assert match, 'deploy/setup.sh: no `pip install -e ".[extras]"` line'
    return tuple(match.group(1).split(","))


def test_make_setup_installs_every_extra() -> None:
    optional = project()["optional-dependencies"]
    assert isinstance(optional, dict)
    assert sorted(setup_extras()) == sorted(optional)


@pytest.mark.parametrize("folder", ["tests", "bench"])
def test_tests_and_benches_import_only_what_make_setup_installs(folder: str) -> None:
    modules = imported_modules(REPO / folder)
    for module in OPTIONAL_TOOLS:
        modules.pop(module, None)
    problems = undeclared(modules, declared(*setup_extras()))
    assert not problems, f"{folder}/ imports packages `make setup` does not install: {problems}"


def test_the_check_sees_an_undeclared_import(tmp_path: Path) -> None:
    """Imports inside functions count, local helpers and the standard library do not, and a
    package outside the declared list is reported."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "helper.py").write_text("X = 1\n")
    (package / "mod.py").write_text(
        "import os\nimport numpy as np\nimport helper\nfrom shared import clock\n\n"
        "def f():\n    from yaml import safe_load\n"
    )
    modules = imported_modules(package)
    assert modules == {"numpy": {"pkg/mod.py"}, "yaml": {"pkg/mod.py"}}
    assert undeclared(modules, {"numpy", "pyyaml"}) == []
    assert undeclared(modules, {"numpy"}) == ["yaml from ['pyyaml'] (imported by ['pkg/mod.py'])"]
    missing = undeclared({"no_such_module_here": {"pkg/mod.py"}}, {"numpy"})
    assert missing == ["no_such_module_here (imported by ['pkg/mod.py']): not installed here"]
