"""A request checked against the task: the observation keys with their shapes and dtypes, finite values, and the
control fields (``episode``, ``reset``, ``step``, ``outcome``, ``observe``, ``full_chunk``).

``decode_request`` is everything the server does with a frame's bytes before the model: it runs on a worker
thread, so a slow or hostile frame never holds up the event loop that serves the other robots.
"""
from __future__ import annotations

import math
import unicodedata
from dataclasses import dataclass, field

import numpy as np

from jepa_policy.policy import Policy
from jepa_policy.serve.codec import MAX_REQUEST_BYTES, RequestError, unpack

CONTROL_FIELDS = (("episode", (str, int)), ("reset", bool), ("step", int), ("outcome", bool), ("observe", bool),
                  ("full_chunk", bool))


@dataclass(frozen=True)
class RequestSchema:
    """What a request must hold: each observation key's shape and dtype, and how many frames a decision uses."""

    task: str
    shapes: dict[str, tuple[tuple[int, ...], str]]
    obs_steps: int
    # low-dim keys: the range of the policy's training data (its normalizer's min and max), per dimension
    ranges: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def of(cls, policy: Policy) -> "RequestSchema":
        spec = policy.spec
        shapes = {k: ((spec.image_size, spec.image_size, 3), "uint8") for k in spec.image_keys}
        shapes.update({k: ((d,), "float32") for k, d in spec.lowdim})
        normalizer = getattr(policy.model, "normalizer", None)
        ranges = {}
        if normalizer is not None and bool(getattr(normalizer, "fitted", False)):
            for key, _ in spec.lowdim:
                if key in normalizer.fields:   # y = x * scale + offset maps the training range onto [-1, 1]
                    scale = normalizer.fields[key].scale.detach().cpu().numpy().astype(np.float64)
                    offset = normalizer.fields[key].offset.detach().cpu().numpy().astype(np.float64)
                    ranges[key] = ((-1.0 - offset) / scale, (1.0 - offset) / scale)
        return cls(spec.name, shapes, policy.obs_steps, ranges)

    def describe(self) -> str:
        return ", ".join(f"{k} {dt}{list(sh)}" for k, (sh, dt) in self.shapes.items())


@dataclass
class Parsed:
    frames: list[dict]            # newest last, unbatched arrays
    episode: str | None
    reset: bool
    step: int | None
    outcome: bool | None
    observe: bool
    full_chunk: bool


def decode_request(message: bytes | str, schema: RequestSchema) -> Parsed:
    """A websocket message -> a checked request; any problem is a RequestError naming it and the fix."""
    if isinstance(message, str):
        raise RequestError("send binary frames packed with msgpack (openpi-client's packer), not text")
    if len(message) > MAX_REQUEST_BYTES:   # websockets refuses these before reading them; a second line of defence
        raise RequestError(f"the request has {len(message)} bytes, above the limit {MAX_REQUEST_BYTES}; send the "
                           "task's observation keys only, at the metadata's shapes")
    return parse_request(unpack(message), schema)


def _text_key(key):
    if not isinstance(key, bytes):
        return key
    try:
        return key.decode()
    except UnicodeDecodeError:
        raise RequestError(f"the map key {key[:32]!r} is not UTF-8 text; keys are the observation names of the "
                           "metadata and the control fields") from None


def parse_request(msg, schema: RequestSchema) -> Parsed:
    """Check a decoded request against the task: keys, shapes, dtypes, finite values, control fields."""
    if not isinstance(msg, dict):
        raise RequestError(f"a request is a map of observation keys, got {type(msg).__name__}")
    msg = {_text_key(k): v for k, v in msg.items()}
    control = {}
    for name, kind in CONTROL_FIELDS:
        value = msg.get(name)
        if isinstance(value, np.generic):
            value = value.item()
        if value is not None and (not isinstance(value, kind) or (kind is int and isinstance(value, bool))):
            raise RequestError(f"'{name}' must be {kind.__name__ if isinstance(kind, type) else 'str or int'}, "
                               f"got {type(value).__name__}")
        control[name] = value
    if control["step"] is not None and not 0 <= control["step"] < 2**31:
        raise RequestError(f"'step' must be an episode step >= 0, got {control['step']}")
    only_control = control["outcome"] is not None or control["reset"]
    present = [k for k in schema.shapes if k in msg]
    if not present and only_control:
        frames: list[dict] = []
    else:
        missing = [k for k in schema.shapes if k not in msg]
        if missing:
            raise RequestError(f"the observation lacks {missing}; task {schema.task} needs {schema.describe()} "
                               "(see the metadata's 'observation')")
        arrays = {key: _observation(key, msg[key], shape, dtype, schema.obs_steps, schema.ranges.get(key))
                  for key, (shape, dtype) in schema.shapes.items()}
        stacked = {k: len(a) for k, a in arrays.items()}
        if len(set(stacked.values())) > 1:
            raise RequestError(f"the keys stack different numbers of frames ({stacked}); send the same number for "
                               "every key")
        frames = [{k: v[i] for k, v in arrays.items()} for i in range(len(arrays[next(iter(arrays))]))]
    return Parsed(frames, _episode_id(control["episode"]), bool(control["reset"]), control["step"],
                  control["outcome"], bool(control["observe"]), bool(control["full_chunk"]))


MAX_EPISODE_ID = 128
# characters no id may hold: control, format (zero-width spaces and joiners, BOMs, bidi overrides that make two
# ids look alike), line and paragraph separators, private-use, surrogates and unassigned code points
_FORBIDDEN = ("Cc", "Cf", "Zl", "Zp", "Co", "Cs", "Cn")
# characters a reader sees nothing of: combining marks with no base, and the blank letters (Hangul fillers,
# the braille blank)
_MARKS = ("Mn", "Me", "Mc")
_BLANK = frozenset("\u115f\u1160\u3164\uffa0\u2800")


def _episode_id(episode) -> str | None:
    """The request's episode id as text. Refused, never cut or cleaned: a bool; an id with a control, format or
    other invisible code point (two ids that look alike would be two episodes); one with nothing a reader can see
    (spaces, combining marks, blank letters only); one longer than MAX_EPISODE_ID characters (two long ids with
    one prefix would be one episode)."""
    if episode is None:
        return None
    if isinstance(episode, bool):
        raise RequestError(f"'episode' is {episode}, a bool; send an id (str or int), or leave the field out")
    text = str(episode)
    if len(text) > MAX_EPISODE_ID:
        raise RequestError(f"'episode' has {len(text)} characters; send an id of at most {MAX_EPISODE_ID}")
    bad = next((ch for ch in text if unicodedata.category(ch) in _FORBIDDEN), None)
    if bad is not None:
        raise RequestError(f"'episode' contains U+{ord(bad):04X}, a control or invisible character; send an id "
                           "of visible characters (and spaces)")
    if not any(not ch.isspace() and ch not in _BLANK and unicodedata.category(ch) not in _MARKS for ch in text):
        raise RequestError("'episode' is empty (or only whitespace, combining marks or blank letters); send an id "
                           "a reader can see (a new id starts an episode) or leave the field out to stay in the "
                           "current one")
    return text


# a low-dim value more than this many training ranges beyond its training range is refused (4.6e18 for a PushT
# position in pixels was taken); the policy itself sees values a little outside it in normal use
OUT_OF_RANGE_SPANS = 100.0


def _number_lists(key: str, value, shape: tuple[int, ...], dtype: str, obs_steps: int) -> None:
    """A value sent as (nested) lists: refused unless it is numbers nested as ``shape`` or ``[n, *shape]`` with
    n <= obs_steps, checked item by item before numpy sees it (numpy sizes a list of strings as items x the
    longest: 270 KB of them once cost 1 GB)."""
    def refuse(what: str):
        raise RequestError(f"{key} holds {what}; send a numpy array of shape {list(shape)} {dtype} (or a list "
                           "of numbers of that shape)")
    depth, level = 0, value
    while isinstance(level, (list, tuple)):
        depth += 1
        if not level:
            refuse("an empty list")
        level = level[0]
    if depth not in (len(shape), len(shape) + 1):
        refuse(f"lists nested {depth} deep")
    want = shape if depth == len(shape) else (None, *shape)
    limit = math.prod(shape) * obs_steps

    def walk(item, level: int) -> int:
        if level == depth:
            if type(item) not in _NUMBER_TYPES:
                refuse(f"a {type(item).__name__} where a number goes")
            return 1
        if not isinstance(item, (list, tuple)):
            refuse(f"a {type(item).__name__} where a list goes")
        size = want[level]
        if (size is not None and len(item) != size) or (size is None and not 1 <= len(item) <= obs_steps):
            refuse(f"a list of {len(item)} items at depth {level + 1}")
        return sum(walk(x, level + 1) for x in item)
    if walk(value, 0) > limit:
        refuse(f"more than {limit} numbers")


_NUMBER_TYPES = (int, float, bool, np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32,
                 np.uint64, np.float16, np.float32, np.float64)


def _observation(key: str, value, shape: tuple[int, ...], dtype: str, obs_steps: int,
                 trained: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """One observation key as (n, *shape) of its dtype: the newest frame, or the newest n <= obs_steps stacked."""
    if isinstance(value, (list, tuple)):
        _number_lists(key, value, shape, dtype, obs_steps)
    elif not isinstance(value, (np.ndarray, np.generic, int, float)) or isinstance(value, bool):
        raise RequestError(f"{key} is a {type(value).__name__}; send a numpy array of shape {list(shape)} {dtype}")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError):   # a ragged or mixed list
        raise RequestError(f"{key} is not an array (a ragged or mixed list?); send a numpy array of shape "
                           f"{list(shape)} {dtype}") from None
    if arr.shape == shape:
        arr = arr[None]
    elif not (arr.ndim == len(shape) + 1 and arr.shape[1:] == shape and 1 <= arr.shape[0] <= obs_steps):
        raise RequestError(f"{key} has shape {list(arr.shape)}; send {list(shape)} (the newest frame) or "
                           f"[n, {', '.join(map(str, shape))}] with n <= {obs_steps} (the newest frames)")
    if arr.dtype != np.dtype(dtype):
        if dtype == "uint8" or arr.dtype.kind not in "fiu":
            raise RequestError(f"{key} has dtype {arr.dtype}; send {dtype}")
        with np.errstate(over="ignore", invalid="ignore"):   # a value beyond float32 becomes inf: refused below
            arr = arr.astype(dtype)
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise RequestError(f"{key} has NaN or infinite values (or values beyond {dtype}); send finite values")
    if trained is not None:
        lo, hi = trained
        span = np.maximum(hi - lo, 1e-6) * OUT_OF_RANGE_SPANS
        far = (arr < lo - span) | (arr > hi + span)
        if far.any():
            where = np.argwhere(far)[0]
            raise RequestError(f"{key} holds {float(arr[tuple(where)]):.4g} at index {where[1:].tolist()}, far outside "
                               f"the range the policy was trained on ({np.round(lo, 3).tolist()} to "
                               f"{np.round(hi, 3).tolist()}); send the observation in the task's units")
    return arr
