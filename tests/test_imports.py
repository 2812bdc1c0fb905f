"""Services meet on the wire: a service package (services/agent, api, mapper, optimizer,
placerec) imports only ``shared/`` and itself, never another service, and ``shared/``
imports no service. Top-level modules under services/ (CLI, launcher, dashboards) may
import services: they start them. Every import is read with ``ast``, including those
inside functions and relative ones, so a lazy import cannot hide a crossing."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _module_of(path: Path, root: Path) -> list[str]:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return parts[:-1] if parts[-1] == "__init__" else parts


def _imported(node: ast.AST, package: list[str]) -> list[str]:
    """Absolute dotted names an import statement brings in (``from a import b`` gives
    ``a.b`` as well as ``a``: ``b`` may be a submodule)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        base = package[: len(package) - node.level + 1]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    return [mod] + [f"{mod}.{a.name}" for a in node.names if a.name != "*"]


def crossings(root: Path) -> list[str]:
    """Every import under ``root`` that breaks the rule, as ``file:line: owner imports
    target``."""
    services = root / "services"
    out = []
    for path in sorted([*services.rglob("*.py"), *(root / "shared").rglob("*.py")]):
        rel = path.relative_to(root)
        if rel.parts[0] == "services" and len(rel.parts) == 2:
            continue  # top-level CLI / launcher modules may import services
        owner = rel.parts[1] if rel.parts[0] == "services" else "shared"
        mod = _module_of(path, root)
        package = mod if path.name == "__init__.py" else mod[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = set()
            for name in _imported(node, package):
                parts = name.split(".")
                if parts[0] != "services":
                    continue
                if owner == "shared":
                    targets.add(".".join(parts[:2]))
                elif len(parts) > 1 and parts[1] != owner:
                    # Another service, or a launcher module (which imports them all).
                    targets.add(f"services.{parts[1]}")
            out.extend(f"{rel}:{node.lineno}: {owner} imports {t}" for t in sorted(targets))
    return out


def test_no_service_imports_another_and_shared_imports_none():
    bad = crossings(ROOT)
    assert not bad, "imports across services (meet on the wire instead):\n" + "\n".join(bad)


def test_the_checker_flags_crossing_imports(tmp_path: Path):
    files = {
        "services/__init__.py": "",
        "services/cli.py": "from services.alpha import core\nimport services.beta\n",
        "services/alpha/__init__.py": "",
        "services/alpha/core.py": (
            "import json\nfrom shared import util\nfrom . import helper\n"
            "from .helper import f\nfrom services.alpha.helper import g\n"
            "def lazy():\n    from services.beta.thing import x\n"
        ),
        "services/alpha/helper.py": "from .. import beta\n",
        "services/alpha/sub/__init__.py": "from ...beta import thing\n",
        "services/beta/__init__.py": "",
        "services/beta/thing.py": "import services.alpha.core as c\nfrom services import cli\n",
        "shared/__init__.py": "",
        "shared/util.py": "import numpy\nfrom shared import other\n",
        "shared/other.py": "def f():\n    import services.alpha\n",
    }
    for name, text in files.items():
        p = tmp_path / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    assert crossings(tmp_path) == [
        "services/alpha/core.py:7: alpha imports services.beta",
        "services/alpha/helper.py:1: alpha imports services.beta",
        "services/alpha/sub/__init__.py:1: alpha imports services.beta",
        "services/beta/thing.py:1: beta imports services.alpha",
        "services/beta/thing.py:2: beta imports services.cli",
        "shared/other.py:2: shared imports services.alpha",
    ]
