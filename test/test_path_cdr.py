"""``msg_adapters/path_cdr.py``: the packed ``nav_msgs/Path`` is the message ``path_to_msg`` builds (the
bytes deserialise to the same message; CDR padding bytes are not part of it), with its errors."""
from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message

from indoor_loc.errors import InvalidMessageError
from msg_adapters.path import path_to_msg
from msg_adapters.path_cdr import path_cdr


@pytest.mark.parametrize("frame", ["map", "", "ab", "abcdefg", "u1/map"])
def test_path_cdr_is_path_to_msg(frame):
    rng = np.random.default_rng(len(frame))
    for n in (0, 1, 2, 7):
        for yaw in (None, rng.uniform(-4, 4, n)):
            for z in (0.0, 3.5, rng.normal(size=n)):
                stamps = (10**18 + rng.integers(0, 10**12, n)).astype(np.int64)
                xy = rng.normal(size=(n, 2)) * 50
                for head in (None, 12345):
                    want = serialize_message(path_to_msg(stamps, xy, yaw, frame, head, z))
                    got = path_cdr(stamps, xy, yaw, frame, head, z)
                    assert len(got) == len(want)
                    assert deserialize_message(got, Path) == deserialize_message(want, Path)


def test_path_cdr_refuses_what_path_to_msg_refuses():
    xy = np.zeros((2, 2))
    with pytest.raises(InvalidMessageError) as e:
        path_cdr(np.array([1, 2]), np.array([[0.0, np.nan], [0.0, 0.0]]))
    assert e.value.reason == "nan"
    with pytest.raises(InvalidMessageError) as e:
        path_cdr(np.array([-5, 2]), xy)
    assert e.value.reason == "negative_stamp"
    with pytest.raises(InvalidMessageError) as e:
        path_cdr(np.array([1, 2, 3]), xy)
    assert e.value.reason == "shape"
