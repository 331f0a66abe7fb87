"""The compact binary body: msgpack with float32 arrays as raw little-endian bytes (never pickle).

An array travels as the map {"dtype": "<f4", "shape": [d], "data": <d*4 bytes>}; everything else is plain
msgpack. JSON bodies carry arrays as lists of numbers and are decoded to the same Python values.
"""
from __future__ import annotations

import gzip
import json
import math
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import orjson
import numpy as np

MSGPACK_CONTENT_TYPE = "application/x-msgpack"
JSON_CONTENT_TYPE = "application/json"


class BodyError(ValueError):
    """A request body that cannot be decoded; the message says what is wrong and how to fix it."""


def encode_array(array: np.ndarray) -> dict[str, Any]:
    """Wrap a 1-D float array as the binary array map (converted to little-endian float32)."""
    a = np.ascontiguousarray(array, dtype="<f4")
    return {"dtype": "<f4", "shape": list(a.shape), "data": a.tobytes()}


def decode_array(obj: Any) -> np.ndarray:
    """Turn a binary array map back into a float32 array, checking dtype and that the byte count fits the shape."""
    if obj.get("dtype") != "<f4":
        raise BodyError(f"array dtype {obj.get('dtype')!r} is not supported; send little-endian float32 '<f4'")
    shape = obj.get("shape")
    data = obj.get("data")
    if type(shape) is not list or not all(type(d) is int and d >= 0 for d in shape):
        raise BodyError(f"array shape {shape!r} must be a list of non-negative integers")
    if not isinstance(data, (bytes, bytearray)):
        raise BodyError("array 'data' must be raw bytes (msgpack bin)")
    expected = 4 * math.prod(shape)   # a Python product: ~20x quicker than numpy's on a 1-element list
    if len(data) != expected:
        raise BodyError(f"array data has {len(data)} bytes but shape {shape} of float32 needs {expected}")
    array = np.frombuffer(data, dtype="<f4")
    return array if len(shape) == 1 else array.reshape(shape)


def _hook(obj: dict) -> Any:
    if "dtype" in obj and "data" in obj and "shape" in obj:
        return decode_array(obj)
    return obj


def pack(payload: Any) -> bytes:
    """Encode a payload for the binary content type, turning numpy arrays into array maps."""

    def default(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            return encode_array(o)
        raise TypeError(f"cannot encode {type(o).__name__} in a monitor body")

    return msgpack.packb(payload, default=default, use_bin_type=True)


def unpack(body: bytes) -> Any:
    """Decode a binary body; arrays come back as float32 numpy arrays."""
    try:
        return msgpack.unpackb(body, object_hook=_hook, raw=False, strict_map_key=True)
    except BodyError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types for corrupt input
        reason = str(exc) or _MSGPACK_REASONS.get(type(exc).__name__, type(exc).__name__)
        raise BodyError(f"malformed msgpack body ({reason}); encode with monitor_service.encoding.pack") from exc


# msgpack raises these with an empty message
_MSGPACK_REASONS = {"StackError": "nested too deeply: records are flat maps with latents as arrays",
                    "FormatError": "a byte that starts no msgpack value (such as 0xc1)"}


MAX_DEPTH = 16   # a batch is 4 levels deep (body, records, record, latent)


def _keys(payload: Any, limit: int = MAX_DEPTH) -> int | None:
    """The number of keys of all objects, or None when a list or object lies deeper than ``limit`` (an explicit
    stack: no recursion to exhaust)."""
    stack = [(payload, 1)] if isinstance(payload, (list, dict)) else []
    keys = 0
    while stack:
        node, depth = stack.pop()
        if depth > limit:
            return None
        if isinstance(node, dict):
            keys += len(node)
            children = node.values()
        else:
            children = node
        if set(map(type, children)) & {list, dict}:   # C speed over a latent's numbers
            stack.extend((c, depth + 1) for c in children if type(c) in (list, dict))
    return keys


def _shallow(payload: Any, limit: int = MAX_DEPTH) -> bool:
    """Whether no list or object lies deeper than ``limit``."""
    return _keys(payload, limit) is not None


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    """``json``'s object_pairs_hook: an object that names a key twice is refused (JSON parsers keep the last)."""
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        twice = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise BodyError(f"the JSON object names the key {twice[:60]!r} twice; send each field once")
    return obj


def decode_body(body: bytes, content_type: str | None) -> Any:
    """Decode a request body by its content type (JSON or msgpack)."""
    ctype = (content_type or JSON_CONTENT_TYPE).split(";")[0].strip().lower()
    if ctype == MSGPACK_CONTENT_TYPE:
        return unpack(body)
    if ctype in (JSON_CONTENT_TYPE, ""):
        try:
            payload = orjson.loads(body)   # about 10x quicker than json on lists of floats
        except orjson.JSONDecodeError:
            pass   # not strict JSON: the standard parser names the problem (and reads NaN, refused later by field)
        else:
            keys = _keys(payload)
            if keys is None:
                raise BodyError(f"JSON body nested too deeply (over {MAX_DEPTH} levels); records are flat objects with "
                                "latents as lists of numbers")
            # every key is followed by one colon: as many colons as keys means no key was named twice (orjson keeps
            # the last); more colons (some inside strings) take the standard parser, which checks
            if int(np.count_nonzero(np.frombuffer(body, np.uint8) == 58)) != keys:   # 58: ':' (4x bytes.count's speed)
                json.loads(body, object_pairs_hook=_refuse_duplicates)
            return payload
        try:
            return json.loads(body, object_pairs_hook=_refuse_duplicates)
        except BodyError:
            raise
        except ValueError as exc:
            raise BodyError(f"malformed JSON body ({exc}); send a JSON object") from exc
        except RecursionError:
            raise BodyError("JSON body nested too deeply; records are flat objects with latents as lists of "
                            "numbers") from None
    raise BodyError(f"content type {ctype!r} is not supported; use {JSON_CONTENT_TYPE} or {MSGPACK_CONTENT_TYPE}")


def jsonl_rows(path: str | Path, missing: str, layout: str) -> Iterator[tuple[int, Any]]:
    """(line number, value) of every non-blank line of a JSON-lines records file (``.gz`` too). ``missing``: the
    fix named when the file does not exist; ``layout``: what a line must be, named when one is not JSON."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a directory; give the records file in it")
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist; {missing}")
    n = 0
    try:
        with (gzip.open(path, "rt", encoding="utf-8") if path.suffix == ".gz" else path.open(encoding="utf-8")) as f:
            for n, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    yield n, json.loads(line)
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{path}:{n}: not JSON ({exc.msg}); {layout}") from None
    except (EOFError, gzip.BadGzipFile, UnicodeDecodeError, zlib.error) as exc:
        what = ("not a complete gzip file" if path.suffix == ".gz" and not isinstance(exc, UnicodeDecodeError)
                else "not UTF-8 text")
        raise ValueError(f"{path}: {what} after line {n} ({type(exc).__name__}: {exc}); {layout}, written whole "
                         "(a copy cut short? copy it again)") from None
