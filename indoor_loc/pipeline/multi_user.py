"""Any per-user stage as a multi-user stage: one process serves many users (``--multi-user``).

:func:`multi_user` turns a per-user :class:`~indoor_loc.pipeline.stage.Stage` class (``ImuStage``,
``WifiFixStage``, ``PdrKfStage``, ``PfStage``, ``WifiScanStage``) into a ``MULTI_USER`` stage that keeps
one instance of it per user, made on the user's first message by :meth:`Stage.for_user` from a
*template* instance built at start-up. The template holds what every user shares, read-only: the
building graph and its transition table (``tll_pf``), the radio map and its fitted positioner
(``wifi_fix_node``, fitted once, at start-up), the parameters. A user's instance holds only that
user's state — the estimators, its time policy (watermarks, held messages), counters — so a user
costs state, not an interpreter (what each stage keeps per user: docs/scaling.md).

Each message goes to its user's instance through the instance's own :meth:`Stage.process` (or
:meth:`Stage.process_batch` for runs decoded in bulk): time policy, validation, rejections and
outputs are exactly those of a per-user node on the same messages. Outputs are published under
the user's namespace, the per-user node's topics (``/alice/pf/pose``), so consumers do not change.
Rejections and notices are counted and said by the user's instance and, with the user's name, by
the node (its log, its aggregate ``/diagnostics`` status); each user also has a status of its own
(:meth:`MultiUserStage.user_status_stage`; a user that has finished keeps its
last counters for its last status, as a per-user node's last status when it stops).

Which users: the ``users`` list, or every namespace publishing one of the stage's inputs (the
node discovers them), kept if the name matches ``user_pattern`` (a glob) and belongs to this
shard: :func:`shard_of` (a stable hash of the name) modulo ``shard_count`` equals ``shard_index``.
A user whose input publishers have been gone ``user_timeout_s`` has left: its instance finishes
(its end-of-input outputs are published) and is dropped; a user coming back starts afresh.

A user may have parameters of its own (``user_params``: :mod:`indoor_loc.pipeline.user_params`), its
ports included (a robot's ``odom`` for ``pdr/odom``): its instance is made from a template built with
them, one template per distinct set of overrides.
"""
from __future__ import annotations

import dataclasses
import fnmatch
import time
import zlib
from typing import Any, Callable

from indoor_loc.errors import ConfigError
from indoor_loc.params import field, flatten, require
from indoor_loc.pipeline.stage import Output, Port, Stage, namespace_of_user
from indoor_loc.pipeline.user_params import (USER_PARAMS, check_entries, describe, is_pattern, overrides_for,
                                             overrides_key, with_overrides)

#: The parameters a multi-user node adds to its stage's (name, type, default, doc).
MULTI_USER_FIELDS: tuple[tuple[str, type, Any, str], ...] = (
    ("users", list, [], "multi-user: user namespaces to serve; [] = discover them from the ROS graph"),
    ("user_pattern", str, "*", "multi-user: serve only users whose name matches this glob (e.g. 'floor2_*')"),
    ("shard_index", int, 0, "multi-user: this process serves the users whose shard_of(name) % shard_count is this"),
    ("shard_count", int, 1, "multi-user: number of processes (shards) the users are spread over"),
    ("user_timeout_s", float, 10.0, "multi-user: a user whose inputs have had no publisher for this long has "
                                    "left (its end-of-input outputs are published, its state dropped), s; also how "
                                    "long another shard's user may go unserved before it is reported"),
    (USER_PARAMS, dict, {}, "multi-user: per-user parameter overrides, user name or glob -> parameters "
                            "(user_params.robot1.motion_source: odom; docs/scaling.md)"),
)


def shard_of(user: str, shard_count: int) -> int:
    """The shard (0 .. shard_count-1) serving ``user``: CRC-32 of the name (stable across processes,
    machines and Python versions, unlike ``hash``) modulo ``shard_count``."""
    return zlib.crc32(user.strip("/").encode()) % max(1, int(shard_count))


def serves(params: Any, user: str) -> bool:
    """Whether a multi-user node with ``params`` serves ``user`` (pattern and shard)."""
    name = user.strip("/")
    return bool(name) and fnmatch.fnmatchcase(name, params.user_pattern) and \
        shard_of(name, params.shard_count) == params.shard_index


def _validate(self: Any) -> None:
    n = type(self).__name__
    require(self.shard_count >= 1, n, "shard_count", ">= 1", self.shard_count)
    require(0 <= self.shard_index < self.shard_count, n, "shard_index", f"in [0, {self.shard_count})",
            self.shard_index)
    require(self.user_timeout_s > 0, n, "user_timeout_s", "> 0", self.user_timeout_s)
    require(bool(self.user_pattern), n, "user_pattern", "a glob (e.g. '*')", self.user_pattern)
    base = getattr(super(type(self), self), "validate", None)
    if base is not None:
        base()


def multi_user_params(params_cls: type) -> type:
    """``params_cls`` with the multi-user fields added (:data:`MULTI_USER_FIELDS`; those it has already,
    such as the back-end's ``users``, are kept as they are)."""
    have = {f.name for f in dataclasses.fields(params_cls)}
    extra = [(name, tp, field(default, doc)) for name, tp, default, doc in MULTI_USER_FIELDS if name not in have]
    cls = dataclasses.make_dataclass(f"MultiUser{params_cls.__name__}", extra, bases=(params_cls,), frozen=True,
                                     namespace={"validate": _validate, "__module__": __name__})
    cls.__doc__ = f"{params_cls.__doc__ or params_cls.__name__}\n\nMulti-user: {', '.join(n for n, *_ in extra)}."
    return cls


class MultiUserStage(Stage):
    """One instance of :attr:`INNER` per user (see the module doc). Made by :func:`multi_user`."""
    MULTI_USER = True
    INNER: type[Stage] = Stage

    def __init__(self, params: Any, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        #: the shared instance: maps, models and the ports; never given a message
        self.template: Stage = self.INNER(params, namespace=namespace)
        self.notices.extend(self.template.take_notices())
        if not self.template.inputs():
            raise ConfigError(f"{self.NODE_NAME}: with these parameters the stage takes no topic input (e.g. "
                              f"wifi_scan_node with source: iw scans this machine's interface): nothing to serve "
                              f"users from; run it per user instead of --multi-user")
        #: the template of each distinct set of per-user overrides (``user_params``; "" = none: ``template``)
        self.templates: dict[str, Stage] = {overrides_key({}): self.template}
        #: users whose overrides together (several patterns) are not valid parameters: user -> why
        self.refused: dict[str, str] = {}
        #: user -> (its overrides' key, its overrides), resolved when it is first followed, until it leaves
        self._user_key: dict[str, tuple[str, dict[str, Any]]] = {}
        entries = getattr(params, USER_PARAMS, None) or {}
        check_entries(params, frozenset(name for name, *_ in MULTI_USER_FIELDS))
        for key in sorted(entries):         # every entry checked (and its template made) at start-up:
            # a user's name as the user's own parameters, a pattern's alone
            over = flatten(entries[key]) if is_pattern(key) else overrides_for(key, entries)
            self._template_for(over, f"{USER_PARAMS}.{key}")
        self.users: dict[str, Stage] = {}
        #: users whose stage has finished (left, or the node stopping): their last counters, for their
        #: last per-user status (:meth:`user_status_stage`); dropped once the node has said it
        self.ended: dict[str, Ended] = {}
        self.users_left = 0
        for port in self.template.inputs():
            self.on(port.topic, self._unused)
        #: the user whose message is being handled (for the wall time each user takes)
        self.busy_s: dict[str, float] = {}

    @staticmethod
    def _unused(msg: Any, recv_ns: int, user: str) -> list[Output]:
        raise AssertionError("MultiUserStage.process dispatches to the user's own stage")

    # -- per-user parameters (indoor_loc/pipeline/user_params.py) -------------------------------------------
    def _template_for(self, overrides: dict[str, Any], where: str) -> Stage:
        key = overrides_key(overrides)
        st = self.templates.get(key)
        if st is None:
            st = self.INNER(with_overrides(self.params, overrides, where), namespace=self.namespace)
            self.notices.extend(st.take_notices())
            if not st.inputs():
                raise ConfigError(f"{self.NODE_NAME}: {where}: with these parameters the stage takes no topic input")
            for port in st.inputs():
                if not self.handles(port.topic):
                    self.on(port.topic, self._unused)
            self.templates[key] = st
        return st

    def user_overrides(self, user: str) -> dict[str, Any]:
        """The user's parameter overrides (flat; ``{}``: the node's parameters), resolved once."""
        got = self._user_key.get(user)
        if got is None:
            over = overrides_for(user, getattr(self.params, USER_PARAMS, None) or {})
            got = self._user_key[user] = (overrides_key(over), over)
            self._template_for(over, f"{USER_PARAMS} of user {user!r}")
        return got[1]

    def user_template(self, user: str) -> Stage:
        """The template the user's stage is made from (its parameters, its ports)."""
        self.user_overrides(user)
        return self.templates[self._user_key[user][0]]

    def user_params_text(self, user: str) -> str:
        """The user's overrides as its status shows them (``""``: none)."""
        return describe(self.user_overrides(user))

    def user_inputs(self, user: str) -> list[Port]:
        """The user's input ports (relative, as its own per-user node's)."""
        return self.user_template(user).inputs()

    def user_outputs_of(self, user: str) -> list[Port]:
        """The user's output ports under its namespace (absolute: ``/alice/pf/pose``)."""
        return [dataclasses.replace(p, topic=f"/{user}/{p.topic}") for p in self.user_template(user).outputs()]

    # -- ports --------------------------------------------------------------------------------------------
    def inputs(self) -> list[Port]:
        """The inputs of every user's stage: the template's, then those only some users' overrides add."""
        seen: dict[str, Port] = {}
        for st in self.templates.values():
            for p in st.inputs():
                seen.setdefault(p.topic, p)
        return list(seen.values())

    def outputs(self) -> list[Port]:
        return []

    def user_outputs(self) -> list[Port]:
        """The per-user node's outputs, under each user's namespace (absolute: ``/{user}/pf/pose``)."""
        seen: dict[str, Port] = {}
        for st in self.templates.values():
            for p in st.outputs():
                seen.setdefault(p.topic, dataclasses.replace(p, topic="/{user}/" + p.topic))
        return list(seen.values())

    def serves(self, user: str) -> bool:
        """This shard's user (pattern, shard), unless its overrides make no valid parameters (said once)."""
        if not serves(self.params, user) or user in self.refused:
            return False
        try:
            self.user_overrides(user)
        except ConfigError as err:
            self.refused[user] = str(err)
            self.notice(f"user {user!r} is not served: its user_params entries together are not valid: {err}")
            return False
        return True

    # -- users --------------------------------------------------------------------------------------------
    def user_stage(self, user: str) -> Stage:
        """The user's own stage instance (made on first use, sharing the template's read-only parts)."""
        st = self.users.get(user)
        if st is None:
            st = self.users[user] = self.user_template(user).for_user(namespace_of_user(user))
            self.ended.pop(user, None)              # back after leaving: afresh
            st.raw_outputs = self.raw_outputs
            st._reject = self._forwarding_reject(st, user)          # type: ignore[method-assign]
            st.notice = lambda text, user=user: self.notice(f"{user}: {text}")   # type: ignore[method-assign]
            self.busy_s.setdefault(user, 0.0)
        return st

    def user_echoes(self, user: str, topic: str, stamp_ns: int) -> bool:
        """:meth:`Stage.echoes` of the user's stage, or of the stage it finished with (False before its
        first message)."""
        st = self.users.get(user)
        if st is None:                  # finished: its own outputs may still be coming back
            ended = self.ended.get(user)
            return ended is not None and ended.echoes(topic, stamp_ns)
        return st.echoes(topic, stamp_ns)

    def _forwarding_reject(self, st: Stage, user: str) -> Callable[[str, str], None]:
        own = Stage._reject.__get__(st)

        def reject(reason: str, detail: str) -> None:
            own(reason, detail)
            self.diag.now_ns = st.diag.now_ns
            self._reject(reason, f"{user}: {detail}")
        return reject

    @staticmethod
    def _mapped(user: str, outs: list[Output]) -> list[Output]:
        return [(f"/{user}/{t.lstrip('/')}", m) for t, m in outs]

    # -- messages -----------------------------------------------------------------------------------------
    def process(self, topic: str, msg: Any, recv_ns: int, user: str | None = None) -> list[Output]:
        if not user:
            self._reject("no_user", f"{topic}: a multi-user stage needs the message's user")
            return []
        if not self.handles(topic):
            self._reject("unknown_topic", f"no handler for {topic!r}")
            return []
        stats = self.diag.received[topic]
        stats.count += 1
        stats.first_ns = recv_ns if stats.first_ns is None else stats.first_ns
        stats.last_ns = recv_ns
        self.diag.now_ns = recv_ns
        t0 = time.perf_counter()
        outs = self._mapped(user, self.user_stage(user).process(topic, msg, recv_ns))
        took = time.perf_counter() - t0
        self.diag.process_s.append(took)
        self.busy_s[user] += took
        for out_topic, _ in outs:
            self.diag.published[out_topic.split("/", 2)[2]] += 1
        return outs

    def batch_handles(self, topic: str, user: str | None = None) -> bool:
        return (self.user_template(user) if user else self.template).batch_handles(topic)

    def process_user_batch(self, user: str, topic: str, items: list,
                           recv_ns: list[int]) -> list[tuple[int, str, Any]]:
        """:meth:`Stage.process_batch` of the user's own stage (a run of one user's messages)."""
        stats = self.diag.received[topic]
        stats.count += len(items)
        stats.first_ns = recv_ns[0] if stats.first_ns is None else stats.first_ns
        stats.last_ns = recv_ns[-1]
        t0 = time.perf_counter()
        out = [(r, f"/{user}/{t}", m) for r, t, m in self.user_stage(user).process_batch(topic, items, recv_ns)]
        took = time.perf_counter() - t0
        self.diag.process_s.append(took / max(1, len(items)))
        self.busy_s[user] += took
        for _, out_topic, _ in out:
            self.diag.published[out_topic.split("/", 2)[2]] += 1
        return out

    # -- time, ticks, ends (each user's own stage) -------------------------------------------------------------
    def clock_jump_threshold_ns(self) -> int:
        return self.template.clock_jump_threshold_ns()

    def clock_jump(self, back_ns: int, now_ns: int) -> list[Output]:
        outs: list[Output] = []
        for user, st in list(self.users.items()):
            outs += self._mapped(user, st.run_clock_jump(back_ns, now_ns))
        return outs

    def tick(self, now_ns: int) -> list[Output]:
        outs: list[Output] = []
        for user, st in list(self.users.items()):
            outs += self._mapped(user, st.run_tick(now_ns))
        return outs

    def finish_user(self, user: str) -> list[Output]:
        """The user left: its stage's end-of-input outputs, then its state is dropped."""
        st = self.users.pop(user, None)
        if st is None:
            return []
        self.users_left += 1
        outs = self._mapped(user, st.run_finish())
        self.ended[user] = Ended(st)
        self._user_key.pop(user, None)      # resolved again if it comes back
        return outs

    def finish(self) -> list[Output]:
        outs: list[Output] = []
        for user, st in list(self.users.items()):
            outs += self._mapped(user, st.run_finish())
            self.ended[user] = Ended(st)
        return outs

    # -- what the driver sees of a user's input (counted on the node and on the user's own counters) -----
    def count_lost(self, topic: str, n: int, now_ns: int, user: str | None = None) -> None:
        super().count_lost(topic, n, now_ns)
        if user:
            self.user_stage(user).count_lost(topic, n, now_ns)

    def count_missed_at_start(self, topic: str, n: int, user: str | None = None) -> None:
        super().count_missed_at_start(topic, n)
        if user:
            self.user_stage(user).count_missed_at_start(topic, n)

    def reject_input(self, reason: str, detail: str, now_ns: int, user: str | None = None) -> None:
        if not user:
            super().reject_input(reason, detail, now_ns)
            return
        self.user_stage(user).reject_input(reason, detail, now_ns)   # its _reject counts it here too

    def reset_user(self, user: str) -> list[Output]:
        st = self.users.get(user)
        return [] if st is None else self._mapped(user, st.reset_user(""))

    def extra_diagnostics(self) -> dict[str, str]:
        p = self.params
        shown = sorted(self.users)
        out = {"users.count": str(len(shown)), "users": ",".join(shown),
               "users.left": str(self.users_left), "shard": f"{p.shard_index}/{p.shard_count}",
               "user_pattern": p.user_pattern}
        standing = self.template.extra_diagnostics()
        for key in ("error", "warning"):
            if standing.get(key):
                out[key] = standing[key]
        if self.refused:
            out["users.refused"] = ",".join(sorted(self.refused))
            out.setdefault("warning", f"{len(self.refused)} user(s) not served: their user_params are not valid "
                                      f"together ({', '.join(sorted(self.refused)[:5])})")
        return out

    def user_status_stage(self, user: str) -> "Stage | Ended | None":
        """What a user's status is made of: its running stage, or the counters its stage ended with
        (the same keys: a per-user node's last status), or None (followed, no message yet)."""
        return self.users.get(user) or self.ended.get(user)


class Ended:
    """A finished user stage's counters and stage-specific values, as they were when it finished (its
    state is dropped): what :func:`msg_adapters.diagnostics.stage_diagnostics` reads of a stage."""

    def __init__(self, st: Stage) -> None:
        self.namespace = st.namespace
        self.diag = st.diag
        self._extra = dict(st.extra_diagnostics())
        # a stage taking its own output as an input (imu_node's imu/data) still knows its echoes, which
        # may arrive after it finished; no other state is kept
        own = {p.topic for p in st.outputs()} & {p.topic for p in st.inputs()}
        self._echoes: Callable[[str, int], bool] | None = st.echoes if own else None

    def echoes(self, topic: str, stamp_ns: int) -> bool:
        return self._echoes is not None and self._echoes(topic, stamp_ns)

    def extra_diagnostics(self) -> dict[str, str]:
        return self._extra


def multi_user(stage_cls: type[Stage]) -> type[MultiUserStage]:
    """The multi-user stage of a per-user stage class (the same node name, its parameters plus
    :data:`MULTI_USER_FIELDS`)."""
    if stage_cls.MULTI_USER:
        raise TypeError(f"{stage_cls.__name__} is multi-user already")
    return type(f"MultiUser{stage_cls.__name__}", (MultiUserStage,),
                {"INNER": stage_cls, "NODE_NAME": stage_cls.NODE_NAME, "PARAMS": multi_user_params(stage_cls.PARAMS),
                 "STAMP_ORDER": stage_cls.STAMP_ORDER, "__module__": __name__,
                 "__doc__": f"{stage_cls.__name__} for many users in one process (see indoor_loc.pipeline.multi_user)."})
