"""The layout installs: ``msg_adapters/`` (top level, beside ``indoor_loc/``) and ``indoor_loc`` with
``pip install .``, ``pip install -e .`` and the way colcon's ament_python build installs a package
(``setup.py egg_info build install --single-version-externally-managed`` with ``setup.cfg``'s
``lib/indoor_loc`` script dir). Each install is made from a copy of the tree into a temporary prefix
and imported by a fresh interpreter that does not see the source tree."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("indoor_loc", "msg_adapters", "config", "resource", "setup.py", "setup.cfg", "package.xml")
EXECUTABLES = {"imu_node", "wifi_scan_node", "wifi_fix_node", "recorder", "player", "pdr_kf_node", "indoor-loc"}
PROBE = ("import indoor_loc, msg_adapters, msg_adapters.odom, indoor_loc.measurements, indoor_loc.commands.up; "
         "print(indoor_loc.__file__); print(msg_adapters.__file__)")


def _copy_tree(dst: Path) -> Path:
    src = dst / "src"
    src.mkdir()
    for name in SOURCES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(p, src / name)
    return src


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    return env


def _run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=240)


def _probe(site_dir: Path, cwd: Path) -> list[str]:
    """Import both packages in a fresh interpreter whose only extra site dir is ``site_dir``."""
    # the environment running the tests may hold its own editable install of the package (make test's
    # venv): its import finder is dropped and the site dir under test goes first, so only the install
    # under test can answer
    code = ("import site, sys; "
            "sys.meta_path[:] = [f for f in sys.meta_path if not str(getattr(f, '__module__', '')).startswith('__editable__')]; "
            "[sys.modules.pop(m) for m in list(sys.modules) if m.startswith('__editable__')]; "
            f"sys.path.insert(0, {str(site_dir)!r}); site.addsitedir({str(site_dir)!r}); {PROBE}")
    r = _run([sys.executable, "-c", code], cwd)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


def _pip(args: list[str], cwd: Path) -> None:
    # --ignore-installed: without it pip first uninstalls the package from the environment running the
    # tests (the user's own `pip install -e .`, with its `indoor-loc` script) before installing elsewhere
    r = _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--ignore-installed", *args], cwd)
    if r.returncode != 0 and "No matching distribution found for setuptools" in r.stderr:
        pytest.skip("pip's isolated build cannot fetch setuptools on this machine (no package index)")
    assert r.returncode == 0, r.stderr[-3000:]


def _site_packages(prefix: Path) -> Path:
    rel = Path(sysconfig.get_path("purelib")).relative_to(sysconfig.get_path("data"))
    return prefix / rel


def test_pip_install(tmp_path):
    src = _copy_tree(tmp_path)
    target = tmp_path / "target"
    _pip(["--target", str(target), "."], src)
    files = _probe(target, tmp_path)
    assert files[0].startswith(str(target / "indoor_loc")) and files[1].startswith(str(target / "msg_adapters"))
    assert EXECUTABLES <= {p.name for p in (target / "bin").iterdir()}
    assert (target / "share" / "indoor_loc" / "config" / "imu_node.yaml").is_file()


def _env_has_package(cwd: Path) -> bool:
    """Whether the environment running the tests has indoor_loc installed (as `make test`'s venv does)."""
    probe = "import importlib.metadata as m; m.distribution('indoor_loc')"
    return subprocess.run([sys.executable, "-c", probe], cwd=cwd, capture_output=True, timeout=60).returncode == 0


def test_pip_install_editable(tmp_path):
    src = _copy_tree(tmp_path)
    prefix = tmp_path / "prefix"
    installed_before = _env_has_package(tmp_path)
    _pip(["--prefix", str(prefix), "-e", "."], src)
    # installing elsewhere must leave the running environment's own install (and its scripts) alone
    assert _env_has_package(tmp_path) == installed_before
    files = _probe(_site_packages(prefix), tmp_path)
    # editable: the imports resolve to the source tree itself, both packages
    assert files[0] == str(src / "indoor_loc" / "__init__.py")
    assert files[1] == str(src / "msg_adapters" / "__init__.py")


def test_colcon_style_install(tmp_path):
    """What ``colcon build`` runs for an ament_python package (colcon itself is not installed here)."""
    src = _copy_tree(tmp_path)
    build, prefix = tmp_path / "build", tmp_path / "install"
    build.mkdir()
    r = _run([sys.executable, "setup.py", "egg_info", "--egg-base", str(build), "build", "--build-base",
              str(build / "build"), "install", "--prefix", str(prefix), "--record", str(build / "install.log"),
              "--single-version-externally-managed"], src)
    assert r.returncode == 0, r.stderr[-3000:]
    files = _probe(_site_packages(prefix), tmp_path)
    assert files[0].startswith(str(prefix)) and files[1].startswith(str(prefix))
    # `ros2 run indoor_loc <exe>` looks in lib/<package>; ament finds the package by its marker
    assert EXECUTABLES <= {p.name for p in (prefix / "lib" / "indoor_loc").iterdir()}
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "indoor_loc").is_file()
    assert {p.name for p in (prefix / "share" / "indoor_loc" / "config").iterdir()} == \
        {p.name for p in (ROOT / "config").glob("*.yaml")}


def test_worktree_on_pythonpath_imports_both_packages(tmp_path):
    """Running from a checkout with ``PYTHONPATH=<checkout>`` (no install) finds both packages there."""
    env = _env()
    env["PYTHONPATH"] = str(ROOT)
    r = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [str(ROOT / "indoor_loc" / "__init__.py"), str(ROOT / "msg_adapters" / "__init__.py")]
