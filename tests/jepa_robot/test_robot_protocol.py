import msgpack
import numpy as np
import pytest

from jepa_robot import protocol as P


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64, np.int64, np.bool_])
def test_arrays_round_trip_exactly(dtype):
    arr = (np.arange(2 * 3 * 4) % 7).astype(dtype).reshape(2, 3, 4)
    out = P.decode(P.encode({"type": P.STEP, "obs": {"img": arr, "nested": [arr[0], 3.5]}}))
    assert out["v"] == P.PROTOCOL_VERSION
    got = out["obs"]["img"]
    assert got.dtype == arr.dtype and got.shape == arr.shape and np.array_equal(got, arr)
    assert got.flags.writeable
    assert np.array_equal(out["obs"]["nested"][0], arr[0]) and out["obs"]["nested"][1] == 3.5


def test_non_contiguous_and_scalars():
    arr = np.arange(20, dtype=np.float32).reshape(4, 5)[:, ::2]
    out = P.decode(P.encode({"type": P.STEP, "a": arr, "s": np.float32(1.5), "b": np.bool_(True)}))
    assert np.array_equal(out["a"], arr) and out["s"] == 1.5 and out["b"] is True


def test_no_pickle_object_arrays_refused():
    with pytest.raises(P.ProtocolError, match="object arrays"):
        P.encode({"type": P.STEP, "a": np.array([object()], dtype=object)})
    with pytest.raises(P.ProtocolError, match="cannot encode"):
        P.encode({"type": P.STEP, "a": object()})
    forged = msgpack.packb({"v": 1, "type": "step", "a": {"__nd__": True, "dtype": "|O", "shape": [1],
                                                          "data": b"\x00" * 8}})
    with pytest.raises(P.ProtocolError, match="object dtype"):
        P.decode(forged)


def test_truncated_payload_and_garbage_refused():
    forged = msgpack.packb({"v": 1, "type": "step", "a": {"__nd__": True, "dtype": "<f4", "shape": [4],
                                                          "data": b"\x00" * 8}})
    with pytest.raises(P.ProtocolError, match="needs 16"):
        P.decode(forged)
    with pytest.raises(P.ProtocolError, match="undecodable"):
        P.decode(b"\xc1\xff garbage")
    with pytest.raises(P.ProtocolError, match="'v' and 'type'"):
        P.decode(msgpack.packb([1, 2, 3]))


def test_version_check_names_both_versions():
    P.check_version({"v": P.PROTOCOL_VERSION, "type": "hello"})
    with pytest.raises(P.ProtocolError, match=rf"peer speaks v99.*speaks v{P.PROTOCOL_VERSION}"):
        P.check_version({"v": 99, "type": "hello"})
