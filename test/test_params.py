"""Params helpers: strict construction, ROS-style params files, dotted/nested keys."""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.params import (field, flatten, group, leaves, load_params_file, misplaced_keys, node_key_matches,
                               param_docs, params_file_text, params_for_node, params_from_dict, params_to_dict,
                               require, validate_groups)


@dataclass(frozen=True)
class DemoParams:
    gain: float = field(1.0, "gain, 1")
    count: int = field(3, "count")
    name: str = field("a", "name")
    flag: bool = field(False, "flag")

    def validate(self) -> None:
        require(self.gain > 0, "DemoParams", "gain", "> 0", self.gain)


def test_unknown_keys_and_bad_types_fail_loudly():
    with pytest.raises(ConfigError, match="unknown parameter"):
        params_from_dict(DemoParams, {"gian": 2.0})
    with pytest.raises(ConfigError, match="expected a bool"):
        params_from_dict(DemoParams, {"flag": 1})
    with pytest.raises(ConfigError, match=r"DemoParams.gain: expected > 0, got -1.0"):
        params_from_dict(DemoParams, {"gain": -1})
    p = params_from_dict(DemoParams, {"gain": 2, "count": 4.0})
    assert p.gain == 2.0 and isinstance(p.gain, float) and p.count == 4 and isinstance(p.count, int)


def test_params_file_precedence_and_dotted_keys(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("""
/**:
  ros__parameters: {gain: 1.5, wknn.k: 3}
/**/my_node:
  ros__parameters: {count: 7, wknn: {shared_threshold: 0.6}}
/walk07/my_node:
  ros__parameters: {name: w7, wknn.k: 5}
""")
    files = load_params_file(f)
    assert params_for_node(files, "my_node", "/walk07") == {
        "gain": 1.5, "count": 7, "name": "w7", "wknn": {"k": 5, "shared_threshold": 0.6}}
    assert params_for_node(files, "my_node", "/walk08")["wknn"] == {"k": 3, "shared_threshold": 0.6}
    assert params_for_node(files, "my_node")["count"] == 7            # /**/ matches the root namespace too
    assert params_for_node(files, "my_node", "/a/b")["count"] == 7    # and nested namespaces
    assert params_for_node(files, "other_node") == {"gain": 1.5, "wknn": {"k": 3}}


def test_bare_node_keys_apply_only_in_the_root_namespace_as_in_rcl(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("my_node:\n  ros__parameters: {count: 7}\n/*/my_node:\n  ros__parameters: {gain: 2.0}\n")
    files = load_params_file(f)
    assert params_for_node(files, "my_node") == {"count": 7}
    assert params_for_node(files, "my_node", "/alice") == {"gain": 2.0}   # bare key: not for /alice/my_node
    assert params_for_node(files, "my_node", "/a/b") == {}                # * is one namespace token
    assert misplaced_keys(files, "my_node", "/alice") == ["my_node"]
    assert misplaced_keys(files, "my_node") == [] and misplaced_keys(files, "other", "/alice") == []
    assert node_key_matches("/**/my_node", "my_node", "/") and not node_key_matches("/**/my_node", "my_node2", "/x")


def test_written_params_files_reach_namespaced_nodes(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text(params_file_text({"imu_node": {"step_length_m": 0.7}, "wifi_fix_node": {"radiomap": "/m"}},
                                  header="two lines\nof header"))
    assert f.read_text().startswith("# two lines\n# of header\n")
    files = load_params_file(f)
    assert params_for_node(files, "imu_node", "/walk06") == {"step_length_m": 0.7}
    assert params_for_node(files, "wifi_fix_node", "/walk06") == {"radiomap": "/m"}
    assert params_for_node(files, "pdr_kf_node", "/walk06") == {}       # no key reaches a third node


def test_shipped_params_files_reach_namespaced_nodes():
    config = Path(__file__).resolve().parents[1] / "config"
    for path in sorted(config.glob("*_node.yaml")):
        node = path.stem
        files = load_params_file(path)
        assert params_for_node(files, node, "/alice"), f"{path.name} sets nothing for /alice/{node}"
        assert misplaced_keys(files, node, "/alice") == []


def test_bool_is_not_an_int():
    with pytest.raises(ConfigError, match="count: expected int"):
        params_from_dict(DemoParams, {"count": True})
    with pytest.raises(ConfigError, match="gain: expected float"):
        params_from_dict(DemoParams, {"gain": False})


def test_params_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("my_node: {gain: 1}\n")
    with pytest.raises(ConfigError, match="ros__parameters"):
        load_params_file(bad)
    clash = tmp_path / "clash.yaml"
    clash.write_text("n:\n  ros__parameters: {wknn: 3, wknn.k: 4}\n")
    with pytest.raises(ConfigError, match="wknn"):
        load_params_file(clash)
    with pytest.raises(ConfigError, match="cannot read"):
        load_params_file(tmp_path / "missing.yaml")


# -- nested Params groups ---------------------------------------------------------------------------
@dataclass(frozen=True)
class InnerParams:
    window_s: float = field(2.0, "window, s")
    taps: int = field(4, "taps")

    def validate(self) -> None:
        require(self.window_s > 0, "InnerParams", "window_s", "> 0", self.window_s)


@dataclass(frozen=True)
class OuterParams:
    gain: float = field(1.0, "gain, 1")
    inner: InnerParams = group(InnerParams, "the inner algorithm")
    other: InnerParams = group(InnerParams, "a second instance of it")

    def validate(self) -> None:
        validate_groups(self)


def test_groups_are_static_dataclasses_built_from_nested_or_dotted_keys():
    assert OuterParams().inner == InnerParams() and OuterParams().inner is not OuterParams().inner
    a = params_from_dict(OuterParams, {"inner": {"window_s": 3}, "other.taps": 7})
    assert a == OuterParams(inner=InnerParams(window_s=3.0), other=InnerParams(taps=7))
    assert isinstance(a.inner.window_s, float)
    assert [name for name, _, _ in leaves(OuterParams)] == ["gain", "inner.window_s", "inner.taps",
                                                             "other.window_s", "other.taps"]
    assert param_docs(OuterParams)["other.taps"] == "taps"
    assert params_to_dict(a) == {"gain": 1.0, "inner": {"window_s": 3.0, "taps": 4}, "other": {"window_s": 2.0, "taps": 7}}
    assert params_from_dict(OuterParams, params_to_dict(a)) == a
    assert flatten(params_to_dict(a))["other.taps"] == 7


def test_group_errors_name_the_dotted_path():
    with pytest.raises(ConfigError, match=r"OuterParams.inner: InnerParams.window_s: expected > 0"):
        params_from_dict(OuterParams, {"inner.window_s": -1.0})
    with pytest.raises(ConfigError, match=r"did you mean \['inner.taps', 'other.taps'\]"):
        params_from_dict(OuterParams, {"taps": 3})           # a leaf given at the top level
    with pytest.raises(ConfigError, match="OuterParams.inner: InnerParams: unknown parameter"):
        params_from_dict(OuterParams, {"inner": {"tapz": 3}})
    with pytest.raises(ConfigError, match="expected a mapping of InnerParams parameters"):
        params_from_dict(OuterParams, {"inner": 5})
    with pytest.raises(ConfigError, match="InnerParams.window_s"):  # a directly built object is checked as deep
        OuterParams(inner=InnerParams(window_s=0.0)).validate()


def test_params_files_merge_groups_per_leaf(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("""
/**:
  ros__parameters: {inner: {window_s: 5.0, taps: 2}}
/**/outer_node:
  ros__parameters: {inner.taps: 9}
""")
    values = params_for_node(load_params_file(f), "outer_node", "/alice")
    assert params_from_dict(OuterParams, values).inner == InnerParams(window_s=5.0, taps=9)


@dataclass(frozen=True)
class TunedParams:
    inner: InnerParams = group(InnerParams, "inner with other defaults", default=InnerParams(taps=8))


def test_a_group_may_carry_its_own_defaults_and_leaves_merge_over_them():
    assert TunedParams().inner == InnerParams(taps=8)
    assert [(n, d) for n, _, d in leaves(TunedParams)] == [("inner.window_s", 2.0), ("inner.taps", 8)]
    assert params_from_dict(TunedParams, {"inner": {"window_s": 3.0}}).inner == InnerParams(window_s=3.0, taps=8)


# -- one type check for every stage's parameters ----------------------------------------------------
def _typed_leaves(cls: type, prefix: str = ""):
    """(dotted name, owner class name, leaf name, declared type, default) of every plain parameter."""
    import dataclasses

    from indoor_loc.params import field_default, field_types, group_class
    types = field_types(cls)
    for f in dataclasses.fields(cls):
        sub = group_class(f)
        if sub is not None:
            yield from _typed_leaves(sub, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", cls.__name__, f.name, types[f.name], field_default(f)


def _stage_params():
    from indoor_loc.pipeline.registry import STAGES, stage_class
    return [stage_class(name).PARAMS for name in STAGES]


@pytest.mark.parametrize("params_cls", _stage_params(), ids=lambda c: c.__name__)
def test_every_int_parameter_refuses_a_fraction_a_bool_and_a_string(params_cls):
    ints = [leaf for leaf in _typed_leaves(params_cls) if leaf[3] is int]
    for dotted, owner, name, _, default in ints:
        for bad, got in ((default + 0.5, f"{default + 0.5!r} (float)"), (True, "True (bool)"),
                         (str(default), f"{str(default)!r} (str)")):
            with pytest.raises(ConfigError, match=re.escape(f"{owner}.{name}: expected int")) as err:
                params_from_dict(params_cls, {dotted: bad})
            assert got in str(err.value), (dotted, str(err.value))
        # a float with no fraction is the int it spells (a YAML `k: 4.0`)
        value = params_from_dict(params_cls, {dotted: float(default)})
        for part in dotted.split("."):
            value = getattr(value, part)
        assert value == default and type(value) is int, dotted


def test_the_stages_have_int_parameters_and_their_types_resolve():
    counts = {cls.__name__: sum(leaf[3] is int for leaf in _typed_leaves(cls)) for cls in _stage_params()}
    assert counts["PfStageParams"] >= 6 and counts["WifiFixParams"] >= 10 and counts["ImuStageParams"] >= 3, counts


def test_a_float_parameter_takes_an_int_and_list_elements_are_checked():
    from indoor_loc.pipeline.pf_stage import PfStageParams
    from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams
    from indoor_loc.pipeline.wifi_scan_stage import WifiScanParams
    p = params_from_dict(PfStageParams, {"max_fix_delay_s": 2})
    assert p.max_fix_delay_s == 2.0 and type(p.max_fix_delay_s) is float
    w = params_from_dict(WifiFixParams, {"pathloss.n_bounds": [1, 4]})
    assert w.pathloss.n_bounds == [1.0, 4.0] and all(type(v) is float for v in w.pathloss.n_bounds)
    with pytest.raises(ConfigError, match=re.escape("PathLossParams.n_bounds[1]: expected float, got 'x' (str)")):
        params_from_dict(WifiFixParams, {"pathloss.n_bounds": [1.5, "x"]})
    with pytest.raises(ConfigError, match=re.escape("NormalizeParams.bands[0]: expected str, got 2.4 (float)")):
        params_from_dict(WifiScanParams, {"normalize.bands": [2.4]})
    with pytest.raises(ConfigError, match=re.escape("PathLossParams.n_bounds: expected a list, got 2.0")):
        params_from_dict(WifiFixParams, {"pathloss.n_bounds": 2.0})


@pytest.mark.parametrize("n", [-5, 0])
def test_a_particle_count_below_one_is_refused(n):
    from indoor_loc.pipeline.pf_stage import PfStageParams
    with pytest.raises(ConfigError, match=re.escape(f"n_particles: expected >= 1, got {n}")):
        params_from_dict(PfStageParams, {"n_particles": n})


def test_a_params_class_with_unresolvable_annotations_is_checked_against_its_defaults():
    @dataclass(frozen=True)
    class Local:
        count: LocalType = field(3, "count")   # noqa: F821 - a name get_type_hints cannot resolve

    with pytest.raises(ConfigError, match=re.escape("Local.count: expected int (a whole number), got 1.5")):
        params_from_dict(Local, {"count": 1.5})
    assert params_from_dict(Local, {"count": 2.0}).count == 2


def test_tll_pf_with_a_fractional_particle_count_exits_2_at_start_up(ros_domain):
    """`tll_pf -p n_particles:=1.5` used to start and then fail every message (internal_error)."""
    import sys

    from helpers_dds import Peer
    peer = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-p", "n_particles:=1.5"])
    try:
        rc = peer.wait(timeout=60)
    finally:
        peer.stop()
    assert rc == 2, peer.output()
    assert "configuration error: PfStageParams.n_particles: expected int (a whole number), got 1.5 (float)" \
        in peer.output(), peer.output()
