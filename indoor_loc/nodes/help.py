"""Command lines of the nodes: a stage node's ``--help`` (its parameters and topics, and the
topics other values of a port-changing parameter select), the ``--params-file`` arguments, and
``main()`` of a node with options of its own (recorder, player, view)."""
from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
from typing import Any, Callable, Mapping, Sequence

from indoor_loc.errors import BagError, ConfigError, IndoorLocError
from indoor_loc.params import leaves
from indoor_loc.pipeline.stage import Stage


def params_file_args(argv: list[str]) -> list[str]:
    """The ``--params-file FILE`` arguments inside ``--ros-args`` sections of ``argv``."""
    out, in_ros = [], False
    for i, a in enumerate(argv):
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a == "--params-file" and i + 1 < len(argv):
            out.append(argv[i + 1])
    return out


def _ports_text(ports: Sequence[Any], prefix: str = "") -> str:
    return ", ".join(f"{prefix}{p.topic} [{p.type}]" for p in ports)


def _port_variants(stage: Stage, port_params: Mapping[str, Sequence[Any]], prefix: str) -> tuple[list[str], list[str]]:
    """Help lines (subscriptions, publications) for the topics other values of a parameter select:
    the ports of ``stage`` with each value of ``port_params`` (``{parameter: [other values]}``, top-level
    parameters), compared with its own. Only the ports are asked for (a copy of the stage with the
    other value), so a value that needs files to start (a radio map) is described all the same."""
    subs: list[str] = []
    pubs: list[str] = []
    for name, values in port_params.items():
        default = getattr(stage.params, name)
        for lines, ports in ((subs, lambda s: s.inputs()), (pubs, lambda s: s.outputs() + s.user_outputs())):
            said: dict[str, list[Any]] = {}      # what changes -> the values that change it so
            for value in values:
                alt = copy.copy(stage)
                alt.params = dataclasses.replace(stage.params, **{name: value})
                mine, other = ports(stage), ports(alt)
                added = [p for p in other if p not in mine]
                gone = [p for p in mine if p not in other]
                if added and gone:
                    said.setdefault(f"{_ports_text(added, prefix)} instead of {_ports_text(gone, prefix)}", []).append(value)
                elif added or gone:
                    said.setdefault(f"also {_ports_text(added, prefix)}" if added else
                                    f"without {_ports_text(gone, prefix)}", []).append(value)
            for text, vals in said.items():
                lines.append(f"  with {name} {' or '.join(repr(v) for v in vals)} (default {default!r}): {text}")
    return subs, pubs


def node_usage(stage_cls: type[Stage], port_params: Mapping[str, Sequence[Any]] | None = None) -> str:
    """The node's ``--help``: usage, the stage's doc, its parameters and its topics with the default
    parameters, and, for each value of ``port_params`` (``{parameter: [other values]}``), the topics
    that value subscribes or publishes instead or as well."""
    lines = [f"usage: ros2 run indoor_loc {stage_cls.NODE_NAME} [--ros-args -r __ns:=/USER "
             f"--params-file FILE -p NAME:=VALUE ...]", "", (stage_cls.__doc__ or "").strip(), "", "parameters:"]
    for name, f, default in leaves(stage_cls.PARAMS):
        lines.append(f"  {name} (default {default!r}): {f.metadata.get('doc', '')}")
    try:
        stage = stage_cls(stage_cls.PARAMS(), namespace="")
    except IndoorLocError as err:     # a stage that needs files to start still gets its help printed
        lines += ["", f"(topics unavailable with default parameters: {err})"]
        return "\n".join(lines)
    lines.append("")
    per_user = "/<user>/" if stage.MULTI_USER else ""
    subs, pubs = _port_variants(stage, port_params or {}, per_user)
    lines.append("subscribes: " + _ports_text(stage.inputs(), per_user)
                 + (" in every user namespace (parameter users, else discovered)" if per_user else ""))
    lines += subs
    lines.append("publishes:  " + _ports_text(stage.outputs() + stage.user_outputs()) + ", /diagnostics")
    lines += pubs
    if stage_cls.MAP_ODOM is not None:         # the estimators: docs/robots.md
        lines += ["", "robot stack (docs/robots.md):",
                  "  publish_tf (node parameter; default true for tll_pf, else false): also send the map -> <user>/odom "
                  "corrections on /tf [tf2_msgs/msg/TFMessage]",
                  "  transform_tolerance (node parameter, default 1.0 s): /tf stamps are this much after the estimate's",
                  f"  service {'~/<user>/' if stage.MULTI_USER else '~/'}set_pose [nav_msgs/srv/SetMap]: restart at "
                  "initial_pose (map left empty), as an initialpose message",
                  f"  {stage_cls.NODE_NAME} --managed --ros-args ...: a lifecycle node (configure, activate, "
                  "deactivate, cleanup); outputs only while active"]
    return "\n".join(lines)


def run_option_node(prog: str, description: str, add_arguments: Callable[[argparse.ArgumentParser], None],
                    run: Callable[[argparse.Namespace, list[str]], int], args: list[str] | None = None) -> int:
    """``main()`` of a node with its own command-line options (recorder, player): the options come
    before ``--ros-args`` and only what follows goes to rcl (so ``--remap OLD:=NEW`` is not read by
    rcl as a deprecated remapping rule). ``run(options, rcl_args)``; ConfigError/BagError -> exit 2."""
    argv = sys.argv if args is None else args
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_arguments(parser)
    options = parser.parse_args(argv[1:cut])
    try:
        return run(options, argv[:1] + argv[cut:])
    except (ConfigError, BagError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 2
