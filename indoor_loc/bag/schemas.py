"""Message definitions, type hashes and QoS text in the form rosbag2 writes them into MCAP.

- Schema data (encoding ``ros2msg``): the ``.msg`` file of the type, then for every nested type a
  line of 80 ``=``, a line ``MSG: pkg/Name`` and that type's ``.msg`` text, depth first, each type
  once, dependencies of a type in sorted order -- the layout of rosbag2_storage_mcap's
  ``MessageDefinitionCache::get_full_text`` (Jazzy), so readers that split on the delimiter
  (rosbags, Foxglove, ``ros2 bag``) find every type.
- Channel metadata ``offered_qos_profiles``: a YAML list of QoS profiles with enum names in lower
  case (rosbag2 metadata version 9, Jazzy), and ``topic_type_hash`` (``RIHS01_...``).

The ``.msg`` files are looked up in the ament index (a sourced ROS install) and in the ``share/``
of the running Python prefix (a virtual environment with the ROS Python wheels).
"""
from __future__ import annotations

import json
import os
import re
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import yaml

from indoor_loc.errors import BagError

DELIMITER = "=" * 80
# rosbag2's patterns: "pkg/Name" or "pkg/msg/Name"; a field type at the start of a line.
_TYPENAME_RE = re.compile(r"^([a-zA-Z][a-zA-Z0-9_]*)/((?:msg|srv)/)?([a-zA-Z][a-zA-Z0-9_]*)$")
_FIELD_TYPE_RE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
                         "int32", "uint32", "int64", "uint64", "string"})

# rmw's "infinite" duration as Fast DDS reports it through the graph API (what ``ros2 bag record``
# then stores for the default deadline / lifespan / liveliness lease).
INFINITE_NS = 9_223_372_036_854_775_807


def _split_type(type_name: str) -> tuple[str, str, str]:
    m = _TYPENAME_RE.match(type_name)
    if m is None:
        raise BagError(f"message type {type_name!r}: expected 'pkg/msg/Name' or 'pkg/Name'")
    return m.group(1), (m.group(2) or "msg/").rstrip("/"), m.group(3)


@lru_cache(maxsize=None)
def _share_dirs(package: str) -> tuple[Path, ...]:
    """Candidate ``share/<package>`` directories: ament index first, then the Python prefixes."""
    dirs: list[Path] = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            dirs.append(Path(get_package_share_directory(package)))
        except (PackageNotFoundError, ValueError, OSError):   # OSError: no AMENT_PREFIX_PATH
            pass
    except ImportError:
        pass
    prefixes = [os.environ.get("VIRTUAL_ENV", ""), sys.prefix, sys.base_prefix]
    prefixes += os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    for prefix in prefixes:
        if prefix:
            p = Path(prefix) / "share" / package
            if p.is_dir() and p not in dirs:
                dirs.append(p)
    return tuple(dirs)


def _interface_file(type_name: str, suffix: str) -> Path | None:
    package, kind, name = _split_type(type_name)
    for d in _share_dirs(package):
        p = d / kind / f"{name}{suffix}"
        if p.is_file():
            return p
    return None


def msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a ``.msg`` text, qualified with ``package`` when bare, sorted."""
    deps = set()
    for m in _FIELD_TYPE_RE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{package}/{t}")
    return sorted(deps)


@lru_cache(maxsize=None)
def _msg_text(type_name: str) -> str:
    p = _interface_file(type_name, ".msg")
    if p is None:
        package = _split_type(type_name)[0]
        raise BagError(f"no .msg definition for {type_name} (looked in {[str(d) for d in _share_dirs(package)]})")
    return p.read_text(encoding="utf-8")


@lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """Full ``ros2msg`` text of ``type_name`` ("sensor_msgs/msg/Imu") with its nested types, as
    rosbag2_storage_mcap concatenates it. Raises BagError when a ``.msg`` file is missing."""
    return _with_dependencies(type_name, _msg_text(type_name), _split_type(type_name)[0])


def _with_dependencies(label: str, text: str, package: str) -> str:
    seen: set[str] = set()

    def append(text: str, package: str, depth: int) -> str:
        if depth <= 0:
            raise BagError(f"message definition of {label} nests too deep")
        out = text
        for dep in msg_dependencies(text, package):
            if dep not in seen:
                seen.add(dep)
                out += f"\n{DELIMITER}\nMSG: {dep}\n" + append(_msg_text(dep), _split_type(dep)[0], depth - 1)
        return out

    return append(text, package, 50)


@lru_cache(maxsize=None)
def service_definitions(type_name: str) -> tuple[str, str]:
    """``ros2msg`` texts of the request and the response of a service type ("std_srvs/srv/Empty"),
    each with its nested types like :func:`message_definition`. Raises BagError when the ``.srv``
    file is missing."""
    p = _interface_file(type_name, ".srv")
    package = _split_type(type_name)[0]
    if p is None:
        raise BagError(f"no .srv definition for {type_name} (looked in {[str(d) for d in _share_dirs(package)]})")
    parts = re.split(r"^---\s*$", p.read_text(encoding="utf-8"), maxsplit=1, flags=re.MULTILINE)
    request, response = (parts + [""])[:2]
    return (_with_dependencies(type_name, request.strip("\n"), package),
            _with_dependencies(type_name, response.strip("\n"), package))


@lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """``RIHS01_...`` hash of the type from its generated ``.json`` description, or "" if absent."""
    p = _interface_file(type_name, ".json")
    if p is None:
        return ""
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    full = "/".join(_split_type(type_name))
    for h in data.get("type_hashes", []):
        if h.get("type_name") == full:
            return str(h.get("hash_string", ""))
    return ""


# -- QoS ------------------------------------------------------------------------------------------
def _duration(ns: int) -> dict[str, int]:
    return {"sec": int(ns) // 1_000_000_000, "nsec": int(ns) % 1_000_000_000}


def qos_dict(*, reliability: str = "reliable", durability: str = "volatile", history: str = "keep_last",
             depth: int = 10, deadline_ns: int = INFINITE_NS, lifespan_ns: int = INFINITE_NS,
             liveliness: str = "automatic", liveliness_lease_ns: int = INFINITE_NS,
             avoid_ros_namespace_conventions: bool = False) -> dict[str, Any]:
    """One QoS profile in rosbag2's version-9 layout (enum names lower case, durations sec/nsec)."""
    return {
        "history": history, "depth": int(depth), "reliability": reliability, "durability": durability,
        "deadline": _duration(deadline_ns), "lifespan": _duration(lifespan_ns), "liveliness": liveliness,
        "liveliness_lease_duration": _duration(liveliness_lease_ns),
        "avoid_ros_namespace_conventions": bool(avoid_ros_namespace_conventions),
    }


def qos_yaml(profiles: Iterable[dict[str, Any]]) -> str:
    """The ``offered_qos_profiles`` channel metadata string (block YAML list; "" for none)."""
    profiles = list(profiles)
    if not profiles:
        return ""
    return yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False).strip()


def parse_qos_yaml(text: str) -> list[dict[str, Any]]:
    """Inverse of :func:`qos_yaml`; also accepts rosbag2's older numeric enums (version <= 8)."""
    if not text or not text.strip():
        return []
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise BagError(f"offered_qos_profiles is not YAML: {err}") from err
    if not isinstance(data, list):
        return []
    numeric = {"reliability": {1: "reliable", 2: "best_effort"},
               "durability": {1: "transient_local", 2: "volatile"},
               "history": {1: "keep_last", 2: "keep_all"}}
    out = []
    for p in data:
        if not isinstance(p, dict):
            continue
        p = dict(p)
        for key, names in numeric.items():
            if isinstance(p.get(key), int):
                p[key] = names.get(p[key], "system_default")
        out.append(p)
    return out
