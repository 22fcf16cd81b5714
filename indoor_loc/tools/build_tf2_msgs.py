"""Build the ``tf2_msgs`` message package into a Python environment that lacks it.

``tf2_msgs`` (the type of ``/tf``: ``tf2_msgs/msg/TFMessage``) has no wheel among the ROS 2 Jazzy
PyPI packages this project installs, while the message generators (``rosidl_adapter``,
``rosidl_generator_c``/``_py``, ``rosidl_typesupport_c``/``_fastrtps_c``/``_introspection_c``), the
runtime headers and libraries of the packages it depends on (``geometry_msgs``, ``std_msgs``,
``builtin_interfaces``) are. This script does what ``rosidl_generate_interfaces`` does in a colcon
build, without CMake/ament: it translates the message definition (shipped in
``indoor_loc/data/tf2_msgs/msg/TFMessage.msg``, the one line of the upstream package) to IDL,
runs each generator on it, compiles the C/C++ sources with the system compiler and installs the
result where the wheels install theirs:

* ``<prefix>/lib/libtf2_msgs__rosidl_{generator_c,typesupport_c,typesupport_fastrtps_c,
  typesupport_introspection_c,generator_py}.so`` (found at run time through the ``LD_LIBRARY_PATH``
  the ROS wheels' bootstrap sets to ``<prefix>/lib``),
* ``<site-packages>/tf2_msgs/`` (the Python package and its three type-support extension modules),
* ``<prefix>/share/tf2_msgs/msg/TFMessage.{msg,idl,json}`` and ``<prefix>/include/tf2_msgs/``,
  plus the ament index entry, for anything that looks the package up.

Usage (``make venv`` runs it): ``.venv/bin/python -m indoor_loc.tools.build_tf2_msgs [--force]``.
Idempotent: it does nothing when ``tf2_msgs.msg.TFMessage`` already imports and was built by this
script from the same sources (``--check`` only reports). Exit status 0 when the type is usable,
1 with the reason on stderr when it could not be built (missing compiler, headers, generators);
the package then still runs, publishing ``map -> odom`` only on its ``TransformStamped`` topic
(``pf/map_odom`` etc.) and not on ``/tf`` (see docs/robots.md).

The script uses no ROS at import time (only when run), so it stays importable anywhere.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

from indoor_loc.errors import ToolchainError

PKG = "tf2_msgs"
DEPS = ("geometry_msgs", "std_msgs", "builtin_interfaces")
MSG_DIR = Path(__file__).resolve().parents[1] / "data" / PKG / "msg"
STAMP_NAME = ".indoor_loc_build"
# header directories of the runtime packages the generated code includes (under <prefix>/include)
RUNTIME_INCLUDES = (
    "rosidl_runtime_c", "rosidl_typesupport_interface", "rcutils", "rosidl_typesupport_c",
    "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "rosidl_typesupport_introspection_c",
    "rosidl_dynamic_typesupport", "rmw", "rosidl_runtime_cpp", "rcpputils",
)  # fastcdr installs its headers flat (<prefix>/include/fastcdr/Cdr.h): <prefix>/include is a root too


def _site_packages(prefix: Path) -> Path:
    return prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"


def _source_digest() -> str:
    h = hashlib.sha256()
    for p in sorted(MSG_DIR.glob("*.msg")) + [Path(__file__)]:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _installed_ok(site: Path) -> bool:
    stamp = site / PKG / STAMP_NAME
    if not stamp.is_file() or stamp.read_text().strip() != _source_digest():
        return False
    return _import_check() is None


def _import_check() -> str | None:
    """Import and serialise TFMessage in a fresh interpreter; None when it works, else the error."""
    code = ("from tf2_msgs.msg import TFMessage\n"
            "from geometry_msgs.msg import TransformStamped\n"
            "from rclpy.serialization import serialize_message, deserialize_message\n"
            "m = TFMessage(transforms=[TransformStamped(child_frame_id='b')])\n"
            "assert deserialize_message(serialize_message(m), TFMessage).transforms[0].child_frame_id == 'b'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    return None if r.returncode == 0 else (r.stderr.strip().splitlines() or ["failed"])[-1]


def _which(*names: str) -> str:
    for n in names:
        found = shutil.which(n)
        if found:
            return found
    raise ToolchainError(f"no {' or '.join(names)} on PATH: install a C/C++ compiler (Debian/Ubuntu: "
                     f"sudo apt install build-essential)")


def _generate(prefix: Path, work: Path) -> dict[str, list[Path]]:
    """Run the rosidl generators; return the generated sources per library."""
    os.environ.setdefault("AMENT_PREFIX_PATH", str(prefix))
    # the wheels register each generator's entry point twice (egg-info + dist-info): harmless, silenced
    logging.getLogger("rosidl_cli.entry_points").setLevel(logging.ERROR)
    try:
        from rosidl_adapter.msg import convert_msg_to_idl
        from rosidl_generator_c.cli import GenerateC
        from rosidl_generator_py.cli import GeneratePython
        from rosidl_typesupport_c.cli import GenerateCTypesupport
        from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
        from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport
    except ImportError as e:
        raise ToolchainError(f"the ROS 2 message generators are not installed in this environment ({e}); "
                         f"install the requirements (ros-jazzy-rclpy pulls them in)") from e
    share = prefix / "share"
    for dep in DEPS:
        if not (share / dep / "msg").is_dir():
            raise ToolchainError(f"{share / dep / 'msg'} missing: the {dep} wheel is not installed")
    pkg_dir = work / "src" / PKG
    (pkg_dir / "msg").mkdir(parents=True)
    msgs = sorted(MSG_DIR.glob("*.msg"))
    for m in msgs:
        shutil.copy(m, pkg_dir / "msg" / m.name)
    idl_root = work / "idl"
    idl_files = []
    for m in msgs:
        with contextlib.redirect_stdout(io.StringIO()):   # "Reading input file ..." chatter
            convert_msg_to_idl(pkg_dir, PKG, Path("msg") / m.name, idl_root / "msg")
        idl_files.append(f"{idl_root}:msg/{m.stem}.idl")
    includes = [str(share / d) for d in DEPS]
    gen = work / "gen"
    out: dict[str, list[Path]] = {}
    for key, cls in (("generator_c", GenerateC), ("typesupport_fastrtps_c", GenerateFastRTPSCTypesupport),
                     ("typesupport_introspection_c", GenerateIntrospectionCTypesupport),
                     ("typesupport_c", GenerateCTypesupport), ("py", GeneratePython)):
        dest = gen / "py" / PKG if key == "py" else gen / key / PKG
        files = cls(key).generate(PKG, idl_files, includes, dest)
        out[key] = [Path(f) for f in files]
    out["idl"] = [idl_root / "msg" / f"{m.stem}.idl" for m in msgs]
    return out


def _compile(cc: str, sources: list[Path], target: Path, includes: list[Path], libdirs: list[Path],
             libs: list[str], cxx: bool) -> None:
    args = [cc, "-shared", "-fPIC", "-O2", "-w", "-o", str(target)]
    args += ["-std=c++17"] if cxx else ["-std=c11"]
    args += [f"-I{p}" for p in includes] + [f"-L{p}" for p in libdirs]
    args += [str(s) for s in sources] + [f"-l{lib}" for lib in libs]
    r = subprocess.run(args, capture_output=True, text=True)
    if r.returncode != 0:
        raise ToolchainError(f"compiling {target.name} failed:\n{' '.join(args)}\n{r.stderr[-4000:]}")


def build(prefix: Path, force: bool = False, verbose: bool = False) -> str:
    """Build and install tf2_msgs into `prefix`; return what was done."""
    site = _site_packages(prefix)
    if not force and _installed_ok(site):
        return f"{PKG} already built in {site}"
    cc, cxx = _which("gcc", "cc"), _which("g++", "c++")
    py_inc = Path(sysconfig.get_paths()["include"])
    if not (py_inc / "Python.h").is_file():
        raise ToolchainError(f"{py_inc}/Python.h missing: install the Python development headers "
                         f"(Debian/Ubuntu: sudo apt install python3-dev)")
    try:
        import numpy
    except ImportError as e:
        raise ToolchainError("numpy is needed by the generated Python bindings") from e
    lib = prefix / "lib"
    inc_root = prefix / "include"
    for name in RUNTIME_INCLUDES + DEPS + ("fastcdr",):
        if not (inc_root / name).is_dir():
            raise ToolchainError(f"{inc_root / name} missing: the ROS runtime headers are not installed")
    with tempfile.TemporaryDirectory(prefix="tf2_msgs_build_") as tmp:
        work = Path(tmp)
        src = _generate(prefix, work)
        gen = work / "gen"
        # generated headers are included as <tf2_msgs/msg/...>: the parent of each tf2_msgs/ is a root
        gen_inc = [gen / k for k in ("generator_c", "typesupport_fastrtps_c", "typesupport_introspection_c")]
        dep_inc = [inc_root / d for d in RUNTIME_INCLUDES + DEPS] + [inc_root]
        includes = gen_inc + dep_inc + [py_inc, Path(numpy.get_include())]
        build_lib = work / "lib"
        build_lib.mkdir()
        libdirs = [build_lib, lib]

        def dep_libs(suffix: str) -> list[str]:
            return [f"{d}__{suffix}" for d in DEPS]

        def srcs(key: str, ext: str) -> list[Path]:
            return [p for p in src[key] if p.suffix == ext]

        base = ["rosidl_runtime_c", "rcutils"]
        steps = [
            ("rosidl_generator_c", srcs("generator_c", ".c"), dep_libs("rosidl_generator_c") + base, False),
            ("rosidl_typesupport_fastrtps_c", srcs("typesupport_fastrtps_c", ".cpp"),
             [f"{PKG}__rosidl_generator_c"] + dep_libs("rosidl_typesupport_fastrtps_c")
             + dep_libs("rosidl_generator_c") + ["rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp",
                                                 "fastcdr", "rmw", "rosidl_dynamic_typesupport"] + base, True),
            ("rosidl_typesupport_introspection_c", srcs("typesupport_introspection_c", ".c"),
             [f"{PKG}__rosidl_generator_c"] + dep_libs("rosidl_typesupport_introspection_c")
             + ["rosidl_typesupport_introspection_c"] + base, False),
            ("rosidl_typesupport_c", srcs("typesupport_c", ".cpp"),
             [f"{PKG}__rosidl_generator_c"] + dep_libs("rosidl_typesupport_c") + ["rosidl_typesupport_c"] + base,
             True),
            ("rosidl_generator_py", [p for p in src["py"] if p.name.endswith("_s.c") and "/msg/" in p.as_posix()],
             [f"{PKG}__rosidl_generator_c", f"{PKG}__rosidl_typesupport_c"] + dep_libs("rosidl_generator_py")
             + dep_libs("rosidl_generator_c") + base, False),
        ]
        for name, sources, libs, is_cxx in steps:
            if not sources:
                raise ToolchainError(f"the generators produced no sources for {name}")
            if verbose:
                print(f"compiling lib{PKG}__{name}.so", flush=True)
            _compile(cxx if is_cxx else cc, sources, build_lib / f"lib{PKG}__{name}.so", includes, libdirs,
                     libs, is_cxx)
        py_root = gen / "py" / PKG
        ext_mods = []
        for ts in ("rosidl_typesupport_c", "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c"):
            ep = py_root / f"_{PKG}_s.ep.{ts}.c"
            target = work / f"{PKG}_s__{ts}.so"
            if verbose:
                print(f"compiling {target.name}", flush=True)
            _compile(cc, [ep], target, includes, libdirs,
                     [f"{PKG}__rosidl_generator_py", f"{PKG}__{ts}", f"{PKG}__rosidl_generator_c", "rmw",
                      "rosidl_runtime_c", "rosidl_typesupport_c", "rosidl_dynamic_typesupport", "rcutils"], False)
            ext_mods.append(target)
        # install: libraries, Python package (replaced whole), share + include + ament index
        for so in sorted(build_lib.glob("*.so")):
            shutil.copy2(so, lib / so.name)
        dest = site / PKG
        staging = site / f".{PKG}.new"
        shutil.rmtree(staging, ignore_errors=True)
        shutil.copytree(py_root, staging, ignore=shutil.ignore_patterns("*.c", "*.h"))
        for so in ext_mods:
            shutil.copy2(so, staging / so.name)
        if not (staging / "__init__.py").exists():
            (staging / "__init__.py").write_text("")
        (staging / STAMP_NAME).write_text(_source_digest() + "\n")
        shutil.rmtree(dest, ignore_errors=True)
        staging.rename(dest)
        share = prefix / "share" / PKG
        (share / "msg").mkdir(parents=True, exist_ok=True)
        for m in sorted(MSG_DIR.glob("*.msg")):
            shutil.copy2(m, share / "msg" / m.name)
        for idl in src["idl"]:
            shutil.copy2(idl, share / "msg" / idl.name)
        for js in (gen / "generator_c" / PKG).rglob("*.json"):
            shutil.copy2(js, share / "msg" / js.name)
        (share / "package.xml").write_text(
            f'<?xml version="1.0"?>\n<package format="3">\n  <name>{PKG}</name>\n  <version>0.0.0</version>\n'
            f'  <description>{PKG} messages generated by indoor_loc.tools.build_tf2_msgs</description>\n'
            f'  <maintainer email="none@example.com">indoor_loc</maintainer>\n  <license>Apache-2.0</license>\n'
            f'  <member_of_group>rosidl_interface_packages</member_of_group>\n</package>\n')
        index = prefix / "share" / "ament_index" / "resource_index"
        for kind, text in (("packages", ""), ("rosidl_interfaces",
                                              "\n".join(f"msg/{m.stem}.msg" for m in sorted(MSG_DIR.glob("*.msg"))))):
            (index / kind).mkdir(parents=True, exist_ok=True)
            (index / kind / PKG).write_text(text)
        inc_dest = inc_root / PKG / PKG
        shutil.rmtree(inc_root / PKG, ignore_errors=True)
        for root in gen_inc:
            shutil.copytree(root / PKG, inc_dest, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("*.c", "*.cpp", "*.json", "tmp"))
    err = _import_check()
    if err is not None:
        raise ToolchainError(f"{PKG} was built into {prefix} but does not import: {err}")
    return f"{PKG} built and installed into {prefix}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prefix", type=Path, default=Path(sys.prefix),
                    help="environment to install into (default: this interpreter's, i.e. the venv)")
    ap.add_argument("--force", action="store_true", help="rebuild even when an up-to-date build imports")
    ap.add_argument("--check", action="store_true", help="only report whether tf2_msgs imports")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    if a.check:
        err = _import_check()
        print(f"{PKG}: " + ("importable" if err is None else f"not importable ({err})"))
        return 0 if err is None else 1
    try:
        print(build(a.prefix.resolve(), force=a.force, verbose=a.verbose))
    except ToolchainError as e:
        print(f"indoor_loc: could not build {PKG}: {e}\n"
              f"Everything else works; without {PKG} the estimators publish map -> odom on their "
              f"TransformStamped topics (e.g. pf/map_odom) but not on /tf (docs/robots.md).", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
