"""MCAP bags in rosbag2's layout: :class:`BagWriter`, :func:`read_bag`, :func:`bag_topics`,
:func:`recover` (see :mod:`indoor_loc.bag.writer`); recorder and player live in ``nodes/``."""
from indoor_loc.bag.writer import (BagMessage, BagWriter, RawMessage, RecoverResult, TopicInfo, bag_files, bag_info,
                                    bag_topics, read_bag, read_raw, recover, scan_records)

__all__ = ["BagMessage", "BagWriter", "RawMessage", "RecoverResult", "TopicInfo", "bag_files", "bag_info", "bag_topics",
           "read_bag", "read_raw", "recover", "scan_records"]
