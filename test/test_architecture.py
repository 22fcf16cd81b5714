"""Keep the layer directions honest by walking every module's imports (AST)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "indoor_loc"
ADAPTERS = ROOT / "msg_adapters"                        # top-level import package beside indoor_loc/
CORE = ("imu", "wifi", "eval", "graph", "fusion", "pf")  # pure numpy/scipy: no ROS at all
ROS_MSG_SUFFIX = "_msgs"


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


CORE_MODULES = ("measurements.py", "errors.py", "params.py")   # core modules at the package's top level


def _modules(sub: str) -> list[Path]:
    if sub.endswith(".py"):
        return [PKG / sub] if (PKG / sub).is_file() else []
    return sorted((PKG / sub).rglob("*.py")) if (PKG / sub).is_dir() else []


@pytest.mark.parametrize("sub", CORE + CORE_MODULES)
def test_core_is_free_of_ros(sub: str) -> None:
    bad = []
    for p in _modules(sub):
        for name in _imports(p):
            top = name.split(".")[0]
            if (top in ("rclpy", "builtin_interfaces", "rosgraph_msgs") or top.endswith(ROS_MSG_SUFFIX)
                    or name.startswith(("msg_adapters", "indoor_loc.pipeline", "indoor_loc.nodes",
                                        "indoor_loc.bag", "indoor_loc.commands"))):
                bad.append(f"{p.relative_to(PKG)} imports {name}")
    assert not bad, "core modules must stay pure:\n" + "\n".join(bad)


def test_only_nodes_and_bag_io_import_rclpy() -> None:
    bad = []
    for p in PKG.rglob("*.py"):
        rel = p.relative_to(PKG).parts
        if rel[0] in ("nodes", "bag", "bench") or p.name in ("demo.py",):
            continue
        if any(n.split(".")[0] == "rclpy" for n in _imports(p)):
            bad.append(str(p.relative_to(PKG)))
    assert not bad, "only nodes (and the bag I/O's serialiser) may import rclpy:\n" + "\n".join(bad)


def test_adapters_do_not_import_stages_or_nodes() -> None:
    bad = [f"{p.name}: {n}" for p in sorted(ADAPTERS.rglob("*.py")) for n in _imports(p)
           if n.startswith(("indoor_loc.pipeline", "indoor_loc.nodes"))]
    assert not bad, bad


def test_adapters_do_not_import_rclpy() -> None:
    bad = [f"{p.name}: {n}" for p in sorted(ADAPTERS.rglob("*.py")) for n in _imports(p) if n.split(".")[0] == "rclpy"]
    assert not bad, "adapters are pure message <-> core functions (no Node, no rclpy.init):\n" + "\n".join(bad)


def _all_modules() -> list[Path]:
    return sorted(PKG.rglob("*.py")) + sorted(ADAPTERS.rglob("*.py"))


def test_one_error_hierarchy() -> None:
    """Every exception class the package defines lives in indoor_loc/errors.py."""
    bad = []
    for p in _all_modules():
        if p == PKG / "errors.py":
            continue
        for node in ast.walk(ast.parse(p.read_text(), filename=str(p))):
            if isinstance(node, ast.ClassDef) and any(
                    (isinstance(b, ast.Name) and (b.id.endswith(("Error", "Exception")))) for b in node.bases):
                bad.append(f"{p.relative_to(ROOT)}: class {node.name}")
    assert not bad, "define exceptions in indoor_loc/errors.py:\n" + "\n".join(bad)


@pytest.mark.parametrize("sub", CORE + CORE_MODULES)
def test_core_raises_core_input_errors_not_message_errors(sub: str) -> None:
    """The core knows no messages: bad input is InvalidInputError (InvalidMessageError is the adapters')."""
    bad = []
    for p in _modules(sub):
        for node in ast.walk(ast.parse(p.read_text(), filename=str(p))):
            if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and \
                    isinstance(node.exc.func, ast.Name) and node.exc.func.id == "InvalidMessageError":
                bad.append(f"{p.relative_to(PKG)}:{node.lineno}")
    assert not bad, "core modules raise InvalidMessageError:\n" + "\n".join(bad)
