"""Every topic a stage reads or writes is in the message contract (``indoor_loc/contract.py``), with
the contract's message type and QoS role, for every stage built from a simulated world's params and
again for each parameter value its node names as changing its topics (``PORT_PARAMS``)."""
from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path

import pytest

from indoor_loc.commands import contract as contract_cmd
from indoor_loc.contract import TOPICS, USER_TOPICS
from indoor_loc.params import load_params_file, params_for_node, params_from_dict
from indoor_loc.pipeline.registry import STAGES, stage_class


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.baro import BaroSimParams
    from indoor_loc.sim.scenario import SimConfig
    out = tmp_path_factory.mktemp("contract_world")
    generate(out, SimConfig(walkers=1, duration_s=10.0, seed=3, baro=BaroSimParams()), quiet=True)
    return out


#: the node module of each stage, whose ``PORT_PARAMS`` name the parameter values that change its topics
NODE_MODULES = {"imu": "imu_node", "wifi": "wifi_fix_node", "wifi_scan": "wifi_scan_node", "pdr_kf": "pdr_kf_node",
                "backend": "backend_node", "pf": "tll_pf_node"}
#: extra parameters a port-changing value needs to build the stage
NEEDS = {("pf", "wifi_update", "scan"): {"radiomap": "radiomap"}}


def _cases() -> list[tuple[str, dict]]:
    """Every stage with its world's params, then once per value its node's ``PORT_PARAMS`` name."""
    cases: list[tuple[str, dict]] = [(name, {}) for name in sorted(STAGES)]
    for name in sorted(STAGES):
        module = importlib.import_module(f"indoor_loc.nodes.{NODE_MODULES[name]}")
        for key, values in getattr(module, "PORT_PARAMS", {}).items():
            cases += [(name, {key: v, **NEEDS.get((name, key, v), {})}) for v in values]
    return cases


CASES = _cases()


def build_stage(world: Path, name: str, overrides: dict):
    """Stage ``name`` with the world's params for ``/walker0`` (``overrides`` on top; a ``radiomap`` is
    relative to the world)."""
    cls = stage_class(name)
    values = params_for_node(load_params_file(world / "params.yaml"), cls.NODE_NAME, "/walker0")
    values = {**values, **{k: str(world / v) if k == "radiomap" else v for k, v in overrides.items()}}
    assert set(overrides) <= {f.name for f in dataclasses.fields(cls.PARAMS)}, overrides
    return cls(params_from_dict(cls.PARAMS, values), namespace="" if cls.MULTI_USER else "/walker0")


@pytest.mark.parametrize(("name", "overrides"), CASES,
                         ids=[n + "".join(f"-{v}" for v in o.values()) for n, o in CASES])
def test_every_port_of_every_stage_is_in_the_contract(world, name, overrides):
    cls = stage_class(name)
    stage = build_stage(world, name, overrides)
    ports = [*stage.inputs(), *stage.outputs()]
    user_ports = list(stage.user_outputs()) if cls.MULTI_USER else []
    assert ports or user_ports
    for port, table in [*((p, TOPICS) for p in ports), *((p, USER_TOPICS) for p in user_ports)]:
        assert port.topic in table, f"{name}: {port.topic} is not in the contract"
        spec = table[port.topic]
        assert (port.type, port.qos) == (spec.type, spec.qos), f"{name}: {port.topic}"


def test_contract_command_prints_the_per_user_topics(capsys):
    assert contract_cmd.main(None) == 0
    out = capsys.readouterr().out
    for name in [*TOPICS, *USER_TOPICS]:
        assert f"| `{name}` |" in out
