"""The nodes' QoS: the contract's profiles by role (:class:`~indoor_loc.contract.Qos`), and the
history depths and reliability the nodes' publishers and subscriptions actually use (sized for
bursts; sensor inputs best effort unless ``sensor_reliability: reliable``). The per-topic overrides
(``qos_overrides./<ns>/<topic>.…`` parameters) are applied by :class:`~indoor_loc.nodes.stage_node.StageNode`."""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from indoor_loc.contract import Qos

QOS_PROFILES: dict[Qos, QoSProfile] = {
    Qos.SENSOR: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                           reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE),
    Qos.RELIABLE: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE),
    Qos.LATCHED: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                            reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL),
    Qos.BEST_EFFORT: QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                                reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE),
}

#: Node parameter (beside the stage's own): reliability of the subscriptions to *sensor* inputs.
SENSOR_RELIABILITY_PARAM = "sensor_reliability"
#: Its values.
RELIABILITY = {"best_effort": ReliabilityPolicy.BEST_EFFORT, "reliable": ReliabilityPolicy.RELIABLE}

#: History depth of the nodes' *subscriptions*, sized for bursts rather than for the steady rate:
#: a replay at 5x, a scheduler hiccup on a loaded machine or a slow first callback must not make
#: DDS overwrite messages the node has not taken yet (2000 IMU samples = 10 s at 200 Hz, ~1 MB).
SUB_DEPTH = {Qos.SENSOR: 2000, Qos.RELIABLE: 1000, Qos.BEST_EFFORT: 100}
#: ... and of reliable sensor inputs (``sensor_reliability: reliable``, a replay): a replay faster than
#: the node can follow on a busy machine queues the difference here (10 000 = 10 s of a 5x replay of a
#: 200 Hz IMU, ~4 MB) instead of overwriting it.
SUB_DEPTH_REPLAY = 10000


def qos_profile(qos: Qos) -> QoSProfile:
    return QOS_PROFILES[qos]


#: History of a *sensor* output's publisher (``imu/data``): being reliable, it keeps what a subscriber
#: has not acknowledged yet, and overwrites the oldest beyond this — a loss for a subscriber starved of
#: CPU for a moment (the recorder during a fast replay). 2000 = 10 s at 200 Hz, 2 s of a 5x replay.
PUB_DEPTH_SENSOR = 2000
#: ... and of a *reliable* output's publisher (``pdr/odom``, ``wifi/fix``, poses): the contract's 50
#: is overrun by a burst of outputs — a node draining its queue at a stop, or catching up after a
#: stall — while a subscriber is starved of CPU (900 drained outputs lost one for a paused
#: subscriber); as deep as a reliable input's subscription (:data:`SUB_DEPTH`).
PUB_DEPTH_RELIABLE = 1000


def publisher_qos(qos: Qos) -> QoSProfile:
    """The QoS an output is published with: the contract's, except that *sensor* outputs are
    published reliable (a reliable writer serves best-effort and reliable readers alike, so a
    node whose sensor inputs were made reliable still hears another node's ``imu/data``), with a
    history of :data:`PUB_DEPTH_SENSOR`, and *reliable* outputs keep :data:`PUB_DEPTH_RELIABLE`."""
    base = QOS_PROFILES[qos]
    if qos == Qos.RELIABLE:
        return QoSProfile(history=base.history, depth=max(base.depth, PUB_DEPTH_RELIABLE),
                          reliability=base.reliability, durability=base.durability)
    if qos != Qos.SENSOR:
        return base
    return QoSProfile(history=base.history, depth=max(base.depth, PUB_DEPTH_SENSOR),
                      reliability=ReliabilityPolicy.RELIABLE, durability=base.durability)


def subscription_qos(qos: Qos, sensor_reliability: str = "best_effort") -> QoSProfile:
    """The contract QoS of an input, with the burst-sized depth of :data:`SUB_DEPTH`; *sensor*
    inputs get ``sensor_reliability`` (``best_effort``, the contract, or ``reliable``)."""
    base = QOS_PROFILES[qos]
    depth = SUB_DEPTH.get(qos, base.depth)
    reliability = RELIABILITY[sensor_reliability] if qos == Qos.SENSOR else base.reliability
    if qos == Qos.SENSOR and reliability == ReliabilityPolicy.RELIABLE:
        depth = SUB_DEPTH_REPLAY
    return QoSProfile(history=base.history, depth=max(depth, base.depth), reliability=reliability,
                      durability=base.durability)
