"""openpi's msgpack-numpy wire (``openpi_client.msgpack_numpy``), checked before anything is built from it.

openpi packs a numpy array as the map ``{b"__ndarray__": True, b"data": raw bytes, b"dtype": dtype.str,
b"shape": shape}`` and a numpy scalar as ``{b"__npgeneric__": True, b"data": item, b"dtype": dtype.str}``. A
frame from the network can name any dtype (``|V8`` with data 400000000 made numpy build a 400 MB scalar) and hold
any number of tiny arrays (190,000 in 8 MiB took 1.5 s to build), so the decoder checks each array's and scalar's
dtype against an allowlist of numeric dtypes and its byte count against its shape before numpy sees it, and a
frame holds at most ``MAX_ARRAYS`` arrays, ``MAX_MAPS`` maps and ``MAX_LIST_ITEMS`` list items: anything within
``MAX_REQUEST_BYTES`` decodes in milliseconds into about its own size. msgpack extension types are refused
(openpi never sends them); msgpack's own timestamps are small fixed-size values that the request check refuses
wherever they appear.
"""
from __future__ import annotations

import math

import msgpack
import numpy as np

MAX_REQUEST_BYTES = 8 * 2**20   # websockets refuses a larger frame from its header, before reading it (code 1009)
MAX_ARRAYS = 64                 # arrays and numpy scalars per request (a task has a few observation keys)
MAX_MAPS = 256                  # maps per request, arrays' own maps included
MAX_LIST_ITEMS = 4096           # items of all lists of a request together (low-dim values sent as lists; a list
                                # longer than this is refused from its header, before msgpack builds its items)
MAX_DIMS = 8
# the dtypes openpi-client packs for observations, as ``dtype.str`` writes them on a little-endian machine
NUMERIC_DTYPES = {np.dtype(t).str: np.dtype(t) for t in (
    np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64,
    np.float16, np.float32, np.float64)}


class RequestError(ValueError):
    """A request the server cannot use; its message goes back to the client as a text frame."""


def _pack_default(obj):
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in ("V", "O", "c"):
        raise TypeError(f"unsupported dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot pack {type(obj).__name__}")


def pack(obj) -> bytes:
    """openpi's ``msgpack_numpy.packb``: arrays as maps with bytes keys, raw little-endian data."""
    return msgpack.packb(obj, default=_pack_default, use_bin_type=True)


def _dtype(name) -> np.dtype:
    if isinstance(name, bytes):
        name = name.decode("ascii", "replace")
    if not isinstance(name, str) or name not in NUMERIC_DTYPES:
        raise RequestError(f"arrays of dtype {str(name)[:40]!r} are refused; send little-endian bool, int, uint or "
                           f"float arrays ({', '.join(NUMERIC_DTYPES)})")
    return NUMERIC_DTYPES[name]


class _Decoder:
    """msgpack's hooks for one frame: counts what it builds and checks every array before numpy builds it."""

    def __init__(self) -> None:
        self.arrays = self.maps = self.list_items = 0

    def object_hook(self, obj: dict):
        self.maps += 1
        if self.maps > MAX_MAPS:
            raise RequestError(f"the request holds more than {MAX_MAPS} maps; send one map of the task's "
                               "observation keys")
        if b"__ndarray__" in obj:
            return self._array(obj)
        if b"__npgeneric__" in obj:
            return self._scalar(obj)
        return obj

    def list_hook(self, items: list) -> list:
        self.list_items += len(items)
        if self.list_items > MAX_LIST_ITEMS:
            raise RequestError(f"the request's lists hold more than {MAX_LIST_ITEMS} items; send observations as "
                               "numpy arrays (openpi-client packs them)")
        return items

    def _count_array(self) -> None:
        self.arrays += 1
        if self.arrays > MAX_ARRAYS:
            raise RequestError(f"the request holds more than {MAX_ARRAYS} arrays; send the task's observation keys "
                               "only (see the metadata's 'observation')")

    def _array(self, obj: dict) -> np.ndarray:
        self._count_array()
        dtype = _dtype(obj.get(b"dtype"))
        shape, data = obj.get(b"shape"), obj.get(b"data")
        if not (isinstance(shape, (list, tuple)) and len(shape) <= MAX_DIMS
                and all(type(s) is int and 0 <= s < 2**31 for s in shape)):
            raise RequestError(f"an array's shape must be a list of at most {MAX_DIMS} sizes >= 0, got "
                               f"{str(shape)[:80]}")
        if not isinstance(data, bytes):
            raise RequestError(f"an array's data must be bytes, got {type(data).__name__}")
        need = math.prod(shape) * dtype.itemsize
        if len(data) != need:
            raise RequestError(f"an array's data has {len(data)} bytes, its shape {list(shape)} of {dtype} needs "
                               f"{need}")
        # a read-only view of the frame's bytes: the request's checks copy what they keep
        return np.frombuffer(data, dtype=dtype).reshape(shape)

    def _scalar(self, obj: dict) -> np.generic:
        self._count_array()
        dtype = _dtype(obj.get(b"dtype"))
        data = obj.get(b"data")
        allowed = {"b": (bool,), "i": (int,), "u": (int,), "f": (int, float)}[dtype.kind]
        if type(data) not in allowed:
            raise RequestError(f"a numpy scalar of dtype {dtype} must carry "
                               f"{' or '.join(t.__name__ for t in allowed)}, got {type(data).__name__}")
        try:
            with np.errstate(over="raise", invalid="raise"):   # a float beyond float16/32: refused, no warning
                return dtype.type(data)
        except (OverflowError, FloatingPointError):
            raise RequestError(f"the numpy scalar {data} does not fit dtype {dtype}") from None


def _refuse_ext(code: int, data: bytes):
    raise RequestError(f"msgpack extension type {code} is refused; pack with openpi-client (numpy arrays as maps)")


def unpack(data: bytes):
    """openpi's ``msgpack_numpy.unpackb``, checked: any decoding problem is a RequestError naming it."""
    decoder = _Decoder()
    try:
        return msgpack.unpackb(data, object_hook=decoder.object_hook, list_hook=decoder.list_hook,
                               ext_hook=_refuse_ext, strict_map_key=False, max_map_len=MAX_MAPS,
                               max_array_len=MAX_LIST_ITEMS)
    except RequestError:
        raise
    except (ValueError, TypeError) as exc:   # msgpack's errors for hostile bytes (bad format, limits, bad keys)
        if "exceeds max_" in str(exc):   # msgpack's own per-container limits, checked from the header
            raise RequestError(f"a list or map of the request is above what a request of this server can hold "
                               f"({exc}); send the task's observation keys only (see the metadata)") from None
        reason = str(exc)[:120] or _EMPTY_REASONS.get(type(exc).__name__, "bad bytes")
        raise RequestError(f"the request is not msgpack as openpi-client packs it ({type(exc).__name__}: "
                           f"{reason})") from None


# msgpack raises these with an empty message
_EMPTY_REASONS = {"FormatError": "a byte that starts no msgpack value (such as 0xc1)",
                  "StackError": "values nested too deep",
                  "ExtraData": "bytes after the first value"}
