"""What each install role of pyproject.toml (``.[client]``, ``.[api]``, ``.[services]``,
``.[worker]``) really installs, and a ``sitecustomize`` that makes every other installed
package unimportable in a process and all its children: a role's commands run in this venv
as they would in an install of that role alone."""

from __future__ import annotations

import json
import re
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[2]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
PROJECT_NAME = canonicalize_name(PROJECT["name"])

SITECUSTOMIZE = """
import importlib.machinery, json, os, sys
_BLOCKED = frozenset(json.loads(open(os.environ["BLOCKED_MODULES_FILE"]).read()))
class _RoleFinder(importlib.machinery.PathFinder):
    # sys.path's finder, not finding the packages the role does not install
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if path is None and name in _BLOCKED:
            return None
        return super().find_spec(name, path, target)
sys.meta_path[:] = [
    _RoleFinder if f is importlib.machinery.PathFinder else f for f in sys.meta_path
]
"""


def role_requirements(role: str) -> list[Requirement]:
    """The project's requirements for ``role`` (its base dependencies plus the extra and
    the extras it names), without the project itself."""
    optional = PROJECT["optional-dependencies"]
    found: list[Requirement] = []
    todo, seen = [role], set()
    while todo:
        extra = todo.pop()
        if extra in seen:
            continue
        seen.add(extra)
        for line in optional[extra]:
            requirement = Requirement(line)
            if canonicalize_name(requirement.name) == PROJECT_NAME:
                todo.extend(requirement.extras)
            else:
                found.append(requirement)
    return [Requirement(line) for line in PROJECT["dependencies"]] + found


def installed_closure(requirements: list[Requirement]) -> set[str]:
    """Names of the installed distributions these requirements pull in, transitively (as
    pip would install them on Linux)."""
    names: set[str] = set()
    todo = [(r, "") for r in requirements]
    while todo:
        requirement, extra = todo.pop()
        environment = {**default_environment(), "extra": extra}
        if requirement.marker is not None and not requirement.marker.evaluate(environment):
            continue
        name = canonicalize_name(requirement.name)
        key = f"{name}[{','.join(sorted(requirement.extras))}]"
        if key in names:
            continue
        names.update({name, key})
        dependencies = metadata.distribution(name).requires or []
        for line in dependencies:
            nested = Requirement(line)
            for wanted in requirement.extras or {""}:
                todo.append((nested, wanted))
    return {n for n in names if "[" not in n}


def blocked_modules(role: str) -> set[str]:
    """Top-level modules of installed distributions that ``role`` does not install."""
    allowed = installed_closure(role_requirements(role)) | {PROJECT_NAME}
    blocked = set()
    for module, distributions in metadata.packages_distributions().items():
        if not re.fullmatch(r"[A-Za-z_]\w*", module) or module == "services":
            continue
        if not {canonicalize_name(d) for d in distributions} & allowed:
            blocked.add(module)
    return blocked


def role_environment(role: str, folder: Path) -> dict[str, str]:
    """Variables that make a Python process (and its children) see only ``role``'s
    packages: a ``sitecustomize`` first on ``PYTHONPATH`` with the repository after it."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(SITECUSTOMIZE)
    listing = folder / "blocked.json"
    listing.write_text(json.dumps(sorted(blocked_modules(role))))
    return {"PYTHONPATH": f"{folder}:{ROOT}", "BLOCKED_MODULES_FILE": str(listing)}
