"""Helpers for the ``XParams`` dataclasses every algorithm and stage declares.

Each Params class is a (frozen) dataclass whose fields carry a ``doc`` in their metadata (units!)
and whose ``validate()`` raises :class:`ConfigError`. Defaults live in one place: nodes declare
their ROS parameters from the fields, offline runs read the same YAML files.
"""
from __future__ import annotations

import dataclasses
import functools
import numbers
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterator, Mapping, TypeVar

import yaml

from indoor_loc.errors import ConfigError

ParamsT = TypeVar("ParamsT")


def field(default: Any, doc: str, **kw: Any) -> Any:
    """A dataclass field with a documentation string (shown as the ROS parameter description)."""
    if isinstance(default, (list, dict)):
        copy: Any = type(default)
        return dataclasses.field(default_factory=lambda: copy(default), metadata={"doc": doc}, **kw)
    return dataclasses.field(default=default, metadata={"doc": doc}, **kw)


def group(cls: type, doc: str, default: Any = None) -> Any:
    """A nested Params group: a field holding a whole ``cls`` Params dataclass (default ``cls()``,
    or ``default``, a frozen ``cls`` object, when the owner wants other defaults for it).

    Its leaves are ROS parameters with dotted names (``stepometer.window_s``), a params file may
    give them as a nested mapping (``stepometer: {window_s: 3.84}``) or dotted keys, values given
    for some leaves keep the group's defaults for the others, and files merge per leaf. Groups nest
    to any depth."""
    factory = cls if default is None else (lambda: default)
    return dataclasses.field(default_factory=factory, metadata={"doc": doc, "group": cls})


def group_class(f: dataclasses.Field[Any]) -> type | None:
    """The Params class of a :func:`group` field, None for a plain field."""
    cls = f.metadata.get("group")
    return cls if isinstance(cls, type) else None


def field_default(f: dataclasses.Field[Any]) -> Any:
    """The default value of a dataclass field (its factory called), None when it has none."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def leaves(cls: type, prefix: str = "", defaults: Any = None) -> Iterator[tuple[str, dataclasses.Field[Any], Any]]:
    """Every plain parameter of a Params class, groups expanded: ``(dotted name, field, default)``
    (a group's leaves default to the group's default object)."""
    for f in dataclasses.fields(cls):
        default = getattr(defaults, f.name) if defaults is not None else field_default(f)
        sub = group_class(f)
        if sub is not None:
            yield from leaves(sub, f"{prefix}{f.name}.", default)
        else:
            yield f"{prefix}{f.name}", f, default


def params_from_dict(cls: type[ParamsT], values: Mapping[str, Any] | ParamsT | None = None) -> ParamsT:
    """Build ``cls(**values)`` (``values`` a mapping, or a ``cls`` object to check again): unknown keys
    and ill-typed values raise ConfigError; then validate().

    Groups (:func:`group`) take a nested mapping or dotted keys (``{"wknn.k": 5}``); a leaf given at
    the wrong level is named in the error with its dotted spelling."""
    given: Any = params_to_dict(values) if isinstance(values, cls) else values or {}
    values = nest_dotted(dict(given), cls.__name__)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields))
    if unknown:
        hints = [f"{n}.{k}" for k in unknown for n, f in fields.items()
                 if (g := group_class(f)) is not None and k in {x.name for x in dataclasses.fields(g)}]
        hint = f" (did you mean {hints}?)" if hints else ""
        raise ConfigError(f"{cls.__name__}: unknown parameter(s) {unknown}{hint}; expected some of {sorted(fields)}")
    declared = field_types(cls)
    for name, value in list(values.items()):
        f = fields[name]
        sub = group_class(f)
        if sub is None:
            values[name] = _coerce(cls.__name__, f, value, declared.get(name))
        elif isinstance(value, Mapping):
            try:   # leaves not given keep the group's default (which may differ from sub())
                values[name] = params_from_dict(sub, {**params_to_dict(field_default(f)), **nest_dotted(value)})
            except ConfigError as err:
                raise ConfigError(f"{cls.__name__}.{name}: {err}") from err
        elif not isinstance(value, sub):
            raise ConfigError(f"{cls.__name__}.{name}: expected a mapping of {sub.__name__} parameters, got {value!r}")
    try:
        obj = cls(**values)
    except TypeError as err:
        raise ConfigError(f"{cls.__name__}: {err}") from err
    validate = getattr(obj, "validate", None)
    if validate is not None:
        validate()
    return obj


def field_types(cls: type) -> dict[str, Any]:
    """``{field name: type}`` of a Params class, resolved (with ``from __future__ import annotations``
    the annotations are strings; :func:`typing.get_type_hints` evaluates them). A class whose annotations
    do not resolve (one defined in a function, naming its local classes) gives {}: its fields are then
    checked against the types of their defaults."""
    return dict(_field_types(cls))


@functools.lru_cache(maxsize=None)
def _field_types(cls: type) -> tuple[tuple[str, Any], ...]:
    try:
        return tuple(typing.get_type_hints(cls).items())
    except (NameError, TypeError):
        return ()


def _coerce(owner: str, f: dataclasses.Field[Any], value: Any, tp: Any = None) -> Any:
    """``value`` as the field's declared type ``tp`` (its annotation), else as the type of its default.

    An int where a float belongs is taken (``step_length_m: 1``), and a float with no fraction where an int
    belongs (``k: 4.0``); a float with one (``n_particles: 1.5``), a bool (an int subclass: ``harmonics: true``
    must not mean 1) or a string where a number belongs are refused, and so are list elements of the wrong
    type. Types this does not know (``list`` without an element type, dicts) are taken as given."""
    where = f"{owner}.{f.name}"
    if value is None:
        return value
    if tp is None or tp is Any:
        default = field_default(f)
        if default is None:
            return value
        tp = type(default)
    return _as_type(where, tp, value)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _as_type(where: str, tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union or origin is types.UnionType:
        if value is None and type(None) in args:
            return None
        alternatives = [a for a in args if a is not type(None)]
        if len(alternatives) == 1:
            return _as_type(where, alternatives[0], value)
        for alt in alternatives:
            try:
                return _as_type(where, alt, value)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected a bool, got {value!r} ({type(value).__name__})")
        return value
    if tp is int:
        if isinstance(value, numbers.Integral) and not isinstance(value, bool):
            return int(value)
        if isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value).is_integer():
            return int(float(value))
        what = " (a whole number)" if isinstance(value, numbers.Real) and not isinstance(value, bool) else ""
        raise ConfigError(f"{where}: expected int{what}, got {value!r} ({type(value).__name__})")
    if tp is float:
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"{where}: expected float, got {value!r} ({type(value).__name__})")
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected str, got {value!r} ({type(value).__name__})")
        return value
    container = origin or tp
    if container in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a {container.__name__}, got {value!r} ({type(value).__name__})")
        if container is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} elements, got {value!r}")
            return tuple(_as_type(f"{where}[{i}]", a, v) for i, (a, v) in enumerate(zip(args, value)))
        elem = args[0] if args else Any
        items = [v if elem is Any else _as_type(f"{where}[{i}]", elem, v) for i, v in enumerate(value)]
        return container(items)
    if isinstance(container, type) and not isinstance(value, container):
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")
    return value


def validate_groups(obj: Any) -> None:
    """Call ``validate()`` of every group of a Params object (a parent's ``validate()`` calls this
    so that a directly constructed object is checked as deeply as :func:`params_from_dict` does)."""
    for f in dataclasses.fields(obj):
        if group_class(f) is not None:
            child = getattr(obj, f.name)
            validate_groups(child)
            validate = getattr(child, "validate", None)
            if validate is not None:
                validate()


def params_to_dict(obj: Any) -> dict[str, Any]:
    """A Params object as a (nested, for groups) dict that :func:`params_from_dict` reads back."""
    return {f.name: params_to_dict(getattr(obj, f.name)) if group_class(f) is not None else getattr(obj, f.name)
            for f in dataclasses.fields(obj)}


def flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"wknn": {"k": 5}}`` -> ``{"wknn.k": 5}`` (the inverse of :func:`nest_dotted`)."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        if isinstance(v, Mapping):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def param_docs(cls: type) -> dict[str, str]:
    """``{dotted name: doc}`` of every plain parameter."""
    return {name: f.metadata.get("doc", "") for name, f, _ in leaves(cls)}


def require(cond: bool, owner: str, name: str, expected: str, got: Any) -> None:
    """``validate()`` helper: raise ConfigError("Owner.name: expected ..., got ...")."""
    if not cond:
        raise ConfigError(f"{owner}.{name}: expected {expected}, got {got!r}")


# ----------------------------------------------------------------------------------------------
# ROS-style parameter files:  {node_name_or_pattern: {"ros__parameters": {...}}}
# ----------------------------------------------------------------------------------------------
def load_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Read a ROS 2 params YAML file. Returns {key: parameters} for every top-level key."""
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot read params file {path}: {err}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"params file {path}: expected a mapping of node names, got {type(data).__name__}")
    out: dict[str, dict[str, Any]] = {}
    for key, body in data.items():
        if not isinstance(body, dict) or "ros__parameters" not in body:
            raise ConfigError(f"params file {path}: entry {key!r} has no 'ros__parameters' mapping")
        out[str(key)] = nest_dotted(dict(body["ros__parameters"] or {}), f"params file {path}: {key}")
    return out


def nest_dotted(values: Mapping[str, Any], where: str = "parameters") -> dict[str, Any]:
    """``{"wknn.k": 5}`` -> ``{"wknn": {"k": 5}}``, merged with nested mappings already there.
    ROS 2 treats the two spellings as the same parameter; offline runs accept both too."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            value = nest_dotted(value, where)
        parts = str(key).split(".")
        node = out
        for part in parts[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(f"{where}: {key!r} nests under {part!r}, which is a plain value")
            node = child
        leaf = parts[-1]
        if isinstance(value, dict) and isinstance(node.get(leaf), dict):
            node[leaf].update(value)
        elif leaf in node and isinstance(node[leaf], dict) != isinstance(value, dict):
            raise ConfigError(f"{where}: {key!r} is given both as a value and as a group")
        else:
            node[leaf] = value
    return out


def node_key(node_name: str) -> str:
    """The params-file key that reaches ``node_name`` in every namespace: ``/**/node_name``.

    rcl matches a bare ``node_name:`` key only to the node in the root namespace (``/node_name``),
    so a file keyed that way is silently ignored by ``--ros-args -r __ns:=/alice``; ``/**:`` would
    reach every node, and a key meant for one node then stops the next ("unknown parameter")."""
    return f"/**/{node_name}"


def params_file_text(nodes: Mapping[str, Mapping[str, Any]], header: str = "") -> str:
    """A ROS 2 params file with one ``/**/node_name:`` section per entry of ``nodes``
    ({node name: {parameter: value}}), preceded by ``header`` (comment lines)."""
    data = {node_key(name): {"ros__parameters": dict(values)} for name, values in nodes.items()}
    text = yaml.safe_dump(data, sort_keys=False)
    return "".join(f"# {line}\n".replace("# \n", "#\n") for line in header.splitlines()) + text


def _key_regex(key: str) -> re.Pattern[str]:
    """rcl's node-key pattern as a regex: ``*`` is one name token, ``/**`` zero or more tokens;
    a key without a leading slash is a name in the root namespace (``node`` = ``/node``)."""
    k = key if key.startswith("/") else "/" + key
    out = []
    i = 0
    while i < len(k):
        if k.startswith("/**", i):
            out.append("(?:/[^/]+)*")
            i += 3
        elif k[i] == "*":
            out.append("[^/]*")
            i += 1
        else:
            out.append(re.escape(k[i]))
            i += 1
    return re.compile("".join(out) + r"\Z")


def node_key_matches(key: str, node_name: str, namespace: str = "") -> bool:
    """Whether a params-file key applies to ``namespace/node_name`` the way rcl decides it."""
    fq = f"{namespace.rstrip('/')}/{node_name}" if namespace.strip("/") else f"/{node_name}"
    if key in ("/**", "**"):
        return True
    return _key_regex(key).match(fq) is not None


#: Parameters of a live node rather than of its stage (rclpy's clock and QoS overrides, the
#: sensor inputs' reliability): accepted in params files and ignored by offline runs.
NODE_LEVEL_PARAMS = ("use_sim_time", "qos_overrides", "sensor_reliability")


def params_for_node(files: Mapping[str, Mapping[str, Any]], node_name: str, namespace: str = "") -> dict[str, Any]:
    """Merge the entries of a params file that apply to ``namespace/node_name``, as rcl matches
    them (see :func:`node_key_matches`): wildcard entries first (``/**``, ``/**/node``), then exact
    fully qualified names. A bare ``node_name:`` key applies only in the root namespace, as live."""
    merged: dict[str, Any] = {}
    ranked: list[tuple[int, int, str]] = []
    for order, key in enumerate(files):
        if node_key_matches(key, node_name, namespace):
            ranked.append((1 if "*" in key else 2, order, key))
    for _, _, key in sorted(ranked):
        _deep_update(merged, files[key])
    for name in NODE_LEVEL_PARAMS:     # the live node's own parameters, not the stage's
        merged.pop(name, None)
    return merged


def misplaced_keys(files: Mapping[str, Mapping[str, Any]], node_name: str, namespace: str = "") -> list[str]:
    """Keys that name this node but do not reach it: a bare ``node_name`` (or ``/node_name``) key
    when the node runs in a namespace. rcl ignores them silently; callers say so loudly."""
    if not namespace.strip("/"):
        return []
    return [k for k in files if k.strip("/") == node_name and not node_key_matches(k, node_name, namespace)]


def _deep_update(into: dict[str, Any], new: Mapping[str, Any]) -> None:
    # parameter groups merge per leaf, as rcl's flat dotted names would
    for k, v in new.items():
        if isinstance(v, Mapping) and isinstance(into.get(k), dict):
            _deep_update(into[k], v)
        else:
            into[k] = dict(v) if isinstance(v, Mapping) else v
