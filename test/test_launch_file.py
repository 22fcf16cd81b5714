"""launch/indoor_loc.launch.py (``launch`` itself is not installable here, so it is read, not run):
it parses, setup.py installs it, every executable it names is one of the package's, every params
file it names exists, and it starts the same nodes as ``indoor-loc up config/bringup_example.yaml``."""
from __future__ import annotations

import ast
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / "launch" / "indoor_loc.launch.py"


def _setup_nodes() -> set[str]:
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "NODES" for t in node.targets):
            return set(ast.literal_eval(node.value))
    raise AssertionError("setup.py defines no NODES")


def _node_calls(tree: ast.AST) -> list[dict]:
    """keyword -> constant (or None when not a constant) of every ``Node(...)`` call."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "Node":
            out.append({k.arg: (k.value.value if isinstance(k.value, ast.Constant) else None)
                        for k in node.keywords})
    return out


def test_launch_file_names_only_existing_executables_and_params_files():
    tree = ast.parse(LAUNCH.read_text(), filename=str(LAUNCH))
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)
    calls = _node_calls(tree)
    exes = [c.get("executable") for c in calls]
    assert exes and all(c.get("package") == "indoor_loc" for c in calls)
    assert set(exes) <= _setup_nodes(), set(exes) - _setup_nodes()
    yamls = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
             and n.value.endswith(".yaml")]
    assert yamls and all((ROOT / "config" / y).is_file() for y in yamls), yamls


def test_launch_file_is_installed():
    """setup.py's data_files put launch/*.launch.py into share/indoor_loc/launch."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    entries = [ast.unparse(t) for n in ast.walk(tree) if isinstance(n, ast.keyword) and n.arg == "data_files"
               for t in n.value.elts]
    assert any("share/{PACKAGE}/launch" in e and "launch/*.launch.py" in e for e in entries), entries


def test_launch_file_matches_the_bringup_example():
    bringup = yaml.safe_load((ROOT / "config" / "bringup_example.yaml").read_text())
    want = sorted(n["executable"] for n in bringup["nodes"])
    got = sorted(c["executable"] for c in _node_calls(ast.parse(LAUNCH.read_text())))
    assert got == want
    # the example's params files are the launch file's too
    files = sorted(f for n in bringup["nodes"] for f in n.get("params_files", []))
    text = LAUNCH.read_text()
    assert files and all(f'"{f}"' in text for f in files)
