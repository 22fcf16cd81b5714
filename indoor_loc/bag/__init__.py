"""MCAP bags in rosbag2's layout, one module per concern as rosbags does: :mod:`.writer`
(:class:`BagWriter`), :mod:`.reader` (:func:`read_bag`, :func:`read_raw`, :func:`bag_info`,
:func:`bag_topics`), :mod:`.recover` (:func:`scan_records`, :func:`recover`), :mod:`.schemas`
(message definitions, QoS text), :mod:`.bulk` (runs of IMU messages decoded into arrays); recorder and player live in ``nodes/``."""
from indoor_loc.bag.reader import (BagMessage, MessageDecoder, RawMessage, TopicInfo, bag_files, bag_info, bag_topics,
                                   read_bag, read_raw)
from indoor_loc.bag.recover import RecoverResult, recover, scan_records
from indoor_loc.bag.writer import BagWriter

__all__ = ["BagMessage", "BagWriter", "MessageDecoder", "RawMessage", "RecoverResult", "TopicInfo", "bag_files", "bag_info", "bag_topics",
           "read_bag", "read_raw", "recover", "scan_records"]
