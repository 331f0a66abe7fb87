"""The integer raster rules the standard Push-T's frames are made with, re-implemented with numpy.

gym-pusht draws its scene on a 512 x 512 pygame surface (pygame 2.6's filled polygons, filled circles, 4-px lines
and anti-aliased lines) and shrinks it with OpenCV's ``cv2.resize`` (INTER_LINEAR). Frames that equal its frames
pixel for pixel need the same integer rules, not only the same geometry, so this module re-states them:

- polygons: a scanline fill at every integer row between the lowest and highest vertex; an edge counts on the
  rows ``[y_top, y_bottom)`` (and on the last row when it ends there) at ``x = trunc(x_top + (y - y_top) * slope)``
  and the sorted crossings are filled pairwise, ends included; horizontal edges strictly inside are filled too;
- filled circles: the midpoint circle algorithm, one row span per step, spans ``[x0 - a, x0 + a - 1]`` (so a
  circle of radius r covers 2r pixels across);
- thick lines: the Bresenham points from end to end, each widened across the line's minor axis by
  ``-(w - 1) // 2 .. w // 2`` pixels (rows for a mostly-horizontal line, columns otherwise);
- anti-aliased lines: Wu's algorithm in single precision, each pixel blended as ``uint8(b * colour + (1 - b) *
  pixel)``;
- the resize: OpenCV's fixed-point bilinear filter (11-bit weights; the vertical pass in its vectorised form
  ``((w0 * (s0 >> 4)) >> 16) + ((w1 * (s1 >> 4)) >> 16) + 2) >> 2``), source columns clamped at the borders and
  source rows clamped after the weights are taken.

``tests/jepa_envs/tasks/test_pusht_raster.py`` checks each rule against its definition; ``make interop`` checks the
frames against gym-pusht's own (docs/envs_pusht_and_data.md, "Parity with gym-pusht").
"""
from __future__ import annotations

import functools
import math

import numpy as np

Spans = tuple[np.ndarray, np.ndarray, np.ndarray]   # rows, first column, last column (inclusive), int64


def polygon_spans(polygons) -> tuple[Spans, np.ndarray]:
    """Row spans of filled polygons with integer vertices (the scanline rule in the module docstring), all the
    polygons of ``polygons`` (a list of (xs, ys) vertex sequences) at once, and the polygon of each span."""
    sizes = np.array([len(xs) for xs, _ in polygons])
    n, p = int(sizes.max()), len(polygons)
    px, py = np.zeros((p, n)), np.zeros((p, n))
    for i, (xs, ys) in enumerate(polygons):
        px[i, :sizes[i]], py[i, :sizes[i]] = xs, ys
    real = np.arange(n)[None, :] < sizes[:, None]
    prev = np.arange(n)[None, :] - 1
    prev = np.where(prev < 0, sizes[:, None] - 1, prev)   # the edge into vertex i comes from vertex i - 1
    ax, ay = np.take_along_axis(px, prev, 1), np.take_along_axis(py, prev, 1)
    top = np.where(real, py, np.inf).min(axis=1)
    bottom = np.where(real, py, -np.inf).max(axis=1)
    sloped = real & (ay != py)
    down = ay < py
    x1, y1 = np.where(down, ax, px)[:, None, :], np.where(down, ay, py)[:, None, :]   # the edge's upper end
    x2, y2 = np.where(down, px, ax)[:, None, :], np.where(down, py, ay)[:, None, :]
    rows = top[:, None] + np.arange(int((bottom - top).max()) + 1)[None, :]
    rows = np.where(rows <= bottom[:, None], rows, np.nan)[:, :, None]
    last = bottom[:, None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        crosses = sloped[:, None, :] & (((rows >= y1) & (rows < y2)) | ((rows == last) & (y2 == last)))
        x = np.sort(np.where(crosses, np.trunc((rows - y1) * (x2 - x1) / (y2 - y1) + x1), np.inf), axis=2)
    counts = crosses.sum(axis=2)
    rows = rows[:, :, 0]
    spanned = top < bottom
    index = np.broadcast_to(np.arange(p)[:, None], counts.shape)
    out_rows, lo, hi, which = [], [], [], []
    for j in range(0, n - 1, 2):
        has = (counts >= j + 2) & spanned[:, None]
        out_rows.append(rows[has])
        lo.append(x[:, :, j][has])
        hi.append(x[:, :, j + 1][has])
        which.append(index[has])
    # horizontal edges strictly between the top and bottom rows are drawn on their own
    flat = real & (ay == py) & (py > top[:, None]) & (py < bottom[:, None])
    out_rows.append(py[flat])
    lo.append(np.minimum(px, ax)[flat])
    hi.append(np.maximum(px, ax)[flat])
    which.append(np.nonzero(flat)[0])
    # a polygon one row high is the row from its leftmost to its rightmost vertex
    out_rows.append(top[~spanned])
    lo.append(np.where(real, px, np.inf).min(axis=1)[~spanned])
    hi.append(np.where(real, px, -np.inf).max(axis=1)[~spanned])
    which.append(np.nonzero(~spanned)[0])
    spans = tuple(np.concatenate(part).astype(np.int64) for part in (out_rows, lo, hi))
    return spans, np.concatenate(which)


def select_spans(spans: Spans, keep: np.ndarray) -> Spans:
    """The spans where ``keep`` is true."""
    return tuple(part[keep] for part in spans)


def concat_spans(*spans: Spans) -> Spans:
    """One span set from several (for one paint of one colour)."""
    return tuple(np.concatenate(part) for part in zip(*spans))


@functools.lru_cache(maxsize=None)
def _circle_offsets(radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row offset, first column offset, last column offset) of a filled circle of ``radius`` at (0, 0)."""
    f, ddf_x, ddf_y, x, y = 1 - radius, 0, -2 * radius, 0, radius
    spans = []
    while x < y:
        if f >= 0:
            y -= 1
            ddf_y += 2
            f += ddf_y
        x += 1
        ddf_x += 2
        f += ddf_x + 1
        if f >= 0:   # the rows at +-y are only drawn when y is about to shrink (each once)
            spans += [(y - 1, -x, x - 1), (-y, -x, x - 1)]
        spans += [(x - 1, -y, y - 1), (-x, -y, y - 1)]
    return tuple(np.array(part, dtype=np.int64) for part in zip(*spans)) if spans else (
        np.zeros(0, np.int64),) * 3


def circle_spans(cx: int, cy: int, radius: int) -> Spans:
    """Row spans of a filled circle centred on integer (cx, cy) (midpoint algorithm); empty for radius < 1."""
    if radius < 1:
        return (np.zeros(0, np.int64),) * 3
    dy, lo, hi = _circle_offsets(int(radius))
    return cy + dy, cx + lo, cx + hi


def bresenham(lines: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Bresenham points of integer segments ``lines`` (L, 4) = (x1, y1, x2, y2), both ends included, in closed
    form: (line index, x, y) per point.

    With the error term started at ``dx // 2`` (x-major) or ``-(dy // 2)`` (y-major), the minor coordinate has
    stepped ``ceil((k * dy - dx // 2) / dx)`` times after k major steps (x-major; y-major mirrored with
    ``ceil((k * dx - dy // 2) / dy)``), at least 0.
    """
    lines = np.asarray(lines, dtype=np.int64).reshape(-1, 4)
    x1, y1, x2, y2 = lines.T
    dx, dy = np.abs(x2 - x1), np.abs(y2 - y1)
    sx, sy = np.where(x1 < x2, 1, -1), np.where(y1 < y2, 1, -1)
    major, minor_d = np.maximum(dx, dy), np.minimum(dx, dy)
    counts = major + 1
    line = np.repeat(np.arange(len(lines)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    m = major[line]
    steps = np.maximum(0, -((m // 2 - k * minor_d[line]) // np.maximum(m, 1)))
    x_major = (dx > dy)[line]
    xs = x1[line] + sx[line] * np.where(x_major, k, steps)
    ys = y1[line] + sy[line] * np.where(x_major, steps, k)
    return line, xs, ys


def clip_segment(x1: int, y1: int, x2: int, y2: int, width: int, height: int) -> tuple[int, int, int, int] | None:
    """The part of an integer segment inside [0, width] x [0, height] (both ends included), its ends rounded half
    away from zero (Liang-Barsky), or None when none of it is."""
    dx, dy = x2 - x1, y2 - y1
    enter, leave = 0.0, 1.0
    for p, q in ((-dx, x1), (dx, width - x1), (-dy, y1), (dy, height - y1)):
        if p == 0:
            if q < 0:
                return None
            continue
        r = q / p
        if p < 0:
            enter = max(enter, r)
        else:
            leave = min(leave, r)
    if enter > leave:
        return None

    def rounded(v: float) -> int:
        return int(v - 0.5) if v < 0 else int(v + 0.5)

    return x1 + rounded(dx * enter), y1 + rounded(dy * enter), x1 + rounded(dx * leave), y1 + rounded(dy * leave)


def _clipped_walk(x1: int, y1: int, x2: int, y2: int, width: int, height: int, offsets: np.ndarray):
    """Centres of a thick line whose ends leave the canvas: the Bresenham walk keeps the error term of the whole
    segment but starts at the clipped start; it runs until both coordinates reach the clipped end, then on toward
    the segment's true end while its cross-section still touches the canvas."""
    dx, dy = abs(x2 - x1), abs(y2 - y1)
    sx, sy = (1 if x1 < x2 else -1), (1 if y1 < y2 else -1)
    err = dx // 2 if dx > dy else -(dy // 2)
    along_rows = dx <= dy
    clipped = clip_segment(x1, y1, x2, y2, width, height)
    if clipped is None:
        return []
    x, y, cx, cy = clipped
    centres = []

    def step():
        nonlocal err, x, y
        e2 = err
        if e2 > -dx:
            err -= dy
            x += sx
        if e2 < dy:
            err += dx
            y += sy

    def touches() -> bool:
        if along_rows:
            return 0 <= y < height and any(0 <= x + o < width for o in (offsets[0], offsets[-1]))
        return 0 <= x < width and any(0 <= y + o < height for o in (offsets[0], offsets[-1]))

    while (x - cx) * sx < 0 or (y - cy) * sy < 0:
        centres.append((x, y))
        step()
    while (y != y2 if along_rows else x != x2) and touches():
        centres.append((x, y))
        step()
    centres.append((x, y))
    return centres


def thick_line_pixels(lines: np.ndarray, width: int, canvas: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """Pixels (rows, columns, line index) of lines ``width`` (>= 2) pixels thick between integer points ``lines``
    (L, 4) on a canvas of (height, width) ``canvas``: each Bresenham point widened across the minor axis (a line at
    least as tall as wide is widened along rows). A line with an end outside [0, width] x [0, height] is walked from
    its clipped start (``_clipped_walk``)."""
    if width < 2:
        raise ValueError(f"thick_line_pixels draws lines of width >= 2, got {width}")
    lines = np.asarray(lines, dtype=np.int64).reshape(-1, 4)
    h, w = canvas
    offsets = np.arange(-((width - 1) // 2), width // 2 + 1, dtype=np.int64)
    inside = ((lines[:, [0, 2]] >= 0) & (lines[:, [0, 2]] <= w)).all(1) & (
        (lines[:, [1, 3]] >= 0) & (lines[:, [1, 3]] <= h)).all(1)
    line, xs, ys = bresenham(lines[inside])
    line = np.flatnonzero(inside)[line]
    for i in np.flatnonzero(~inside):
        centres = _clipped_walk(*(int(v) for v in lines[i]), w, h, offsets)
        if centres:
            line = np.concatenate([line, np.full(len(centres), i)])
            xs = np.concatenate([xs, [c[0] for c in centres]])
            ys = np.concatenate([ys, [c[1] for c in centres]])
    along_rows = (np.abs(lines[:, 0] - lines[:, 2]) <= np.abs(lines[:, 1] - lines[:, 3]))[line][:, None]
    rows = np.where(along_rows, ys[:, None], ys[:, None] + offsets)
    cols = np.where(along_rows, xs[:, None] + offsets, xs[:, None])
    return rows.ravel(), cols.ravel(), np.repeat(line, len(offsets))


class Canvas:
    """A (height, width, 3) uint8 raster that keeps only the pixels at ``rows`` x ``cols`` (all by default).

    Drawing at a pixel that is not kept does nothing, so a canvas that keeps just the pixels a resize reads (see
    ``for_resize``) gives that resize exactly the result a full canvas would, at a fraction of the work (a 96 px
    frame reads 192 of 512 rows and columns)."""

    def __init__(self, background: np.ndarray, rows: np.ndarray | None = None, cols: np.ndarray | None = None):
        h, w = background.shape[:2]
        self.shape = (h, w)
        self.rows = np.arange(h) if rows is None else np.asarray(rows, dtype=np.int64)
        self.cols = np.arange(w) if cols is None else np.asarray(cols, dtype=np.int64)
        self.row_index, self.col_index = np.full(h + 2, -1), np.full(w + 2, -1)   # +2: index -1 and h map to -1
        self.row_index[self.rows] = np.arange(len(self.rows))
        self.col_index[self.cols] = np.arange(len(self.cols))
        self.pixels = np.ascontiguousarray(background[np.ix_(self.rows, self.cols)])

    @classmethod
    def for_resize(cls, background: np.ndarray, width: int, height: int) -> "Canvas":
        """A canvas keeping only the pixels ``resize(width, height)`` reads."""
        h, w = background.shape[:2]
        c0, c1, _, _ = _resize_taps(w, width, True)
        r0, r1, _, _ = _resize_taps(h, height, False)
        return cls(background, np.unique(np.concatenate([r0, r1])), np.unique(np.concatenate([c0, c1])))

    def copy(self) -> "Canvas":
        new = Canvas.__new__(Canvas)
        new.__dict__.update(self.__dict__)
        new.pixels = self.pixels.copy()
        return new

    def _kept(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape
        r = self.row_index[np.clip(rows, -1, h)]
        c = self.col_index[np.clip(cols, -1, w)]
        keep = (r >= 0) & (c >= 0)
        return r[keep], c[keep]

    def paint_spans(self, spans: Spans, color) -> None:
        """Fill row spans (clipped to the canvas) with ``color``."""
        rows, lo, hi = spans
        h, w = self.shape
        r = self.row_index[np.clip(rows, -1, h)]
        first = np.searchsorted(self.cols, np.maximum(lo, 0), "left")
        end = np.searchsorted(self.cols, np.minimum(hi, w - 1), "right")
        keep = (r >= 0) & (end > first)
        r, first, lengths = r[keep], first[keep], (end - first)[keep]
        starts = np.repeat(np.cumsum(lengths) - lengths, lengths)
        self.pixels[np.repeat(r, lengths), np.arange(lengths.sum()) - starts + np.repeat(first, lengths)] = color

    def paint_pixels(self, rows: np.ndarray, cols: np.ndarray, color) -> None:
        """Set pixels (clipped to the canvas) to ``color``."""
        self.pixels[self._kept(rows, cols)] = color

    def blend(self, x: int, y: int, color: np.ndarray, brightness: np.float32) -> None:
        """``pixel = uint8(b * color + (1 - b) * pixel)`` in single precision (pixels outside are skipped)."""
        h, w = self.shape
        if 0 <= x < w and 0 <= y < h and self.row_index[y] >= 0 and self.col_index[x] >= 0:
            r, c = self.row_index[y], self.col_index[x]
            old = self.pixels[r, c].astype(np.float32)
            self.pixels[r, c] = (brightness * color + (np.float32(1) - brightness) * old).astype(np.uint8)

    def resize(self, width: int, height: int) -> np.ndarray:
        """``cv2.resize`` (INTER_LINEAR) of the full canvas to (height, width, 3), bit for bit; every pixel it
        reads must be kept."""
        h, w = self.shape
        c0, c1, cw0, cw1 = _resize_taps(w, width, True)
        r0, r1, rw0, rw1 = _resize_taps(h, height, False)
        rows, left, right = self.row_index[np.concatenate([r0, r1])], self.col_index[c0], self.col_index[c1]
        if (rows < 0).any() or (left < 0).any() or (right < 0).any():
            raise ValueError(f"this canvas does not keep every pixel a resize to {width} x {height} reads")
        return _bilinear(self.pixels, rows, left, right, cw0, cw1, rw0, rw1, width, height)


def aaline(canvas: Canvas, x1: float, y1: float, x2: float, y2: float, color) -> None:
    """Blend an anti-aliased line (Wu's algorithm, single precision) into ``canvas``: the line is clipped to the
    canvas grown by one pixel on every side, each end pixel pair is weighted by how much of its pixel the line
    covers, and every pixel is blended as ``uint8(b * colour + (1 - b) * pixel)``."""
    f32 = np.float32
    color = np.asarray(color, dtype=f32)
    h, w = canvas.shape

    def blend(x: int, y: int, brightness) -> None:
        canvas.blend(x, y, color, f32(brightness))

    fx, fy, tx, ty = f32(x1), f32(y1), f32(x2), f32(y2)
    dx, dy = tx - fx, ty - fy
    if abs(dx) < f32(0.0001) and abs(dy) < f32(0.0001):
        blend(int(math.floor(fx + f32(0.5))), int(math.floor(fy + f32(0.5))), 1.0)
        return
    left, top = f32(-1), f32(-1)
    right, bottom = left + f32(w) + f32(1), top + f32(h) + f32(1)
    steep = abs(dx) < abs(dy)
    if steep:   # walk along y: swap the axes (and the clip bounds with them)
        fx, fy, tx, ty, dx, dy = fy, fx, ty, tx, dy, dx
        left, top, right, bottom = top, left, bottom, right
    if dx < 0:
        fx, fy, tx, ty, dx, dy = tx, ty, fx, fy, -dx, -dy
    if tx <= left or fx >= right:
        return
    gradient = dy / dx
    if fx < left:
        fy, fx = fy + gradient * (left - fx), left
    if tx > right:
        ty, tx = ty + gradient * (right - tx), right
    if gradient > f32(0):
        if ty <= top or fy >= bottom:
            return
        if fy < top:
            fx, fy = fx + (top - fy) / gradient, top
        if ty > bottom:
            tx, ty = tx + (bottom - ty) / gradient, bottom
    else:
        if fy <= top or ty >= bottom:
            return
        if ty < top:
            tx, ty = tx + (top - ty) / gradient, top
        if fy > bottom:
            fx, fy = fx + (bottom - fy) / gradient, bottom
    # rows are shifted down by one so that int() truncation acts as floor, and drawn one higher
    fy, ty = fy + f32(1), ty + f32(1)

    def plot(major: int, minor: int, brightness) -> None:
        if steep:
            blend(minor, major, brightness)
        else:
            blend(major, minor, brightness)

    def endpoint(x_pixel: int, y_end, gap) -> None:
        brightness = y_end - f32(int(y_end))
        if int(y_end) < y_end:
            plot(x_pixel, int(y_end), brightness * gap)
        plot(x_pixel, int(y_end) - 1, (f32(1) - brightness) * gap)

    x_start = int(fx)
    intersect = fy + gradient * f32(x_start - fx)
    if tx > left + f32(1):
        endpoint(x_start, intersect, f32(1 + x_start) - fx)
        intersect = intersect + gradient
        x_start += 1
    x_end = int(math.ceil(tx))
    if fx < right - f32(1):
        endpoint(x_end, ty + gradient * f32(x_end - tx), f32(1 - x_end) + tx)
    for x in range(x_start, x_end):
        y = int(intersect)
        brightness = f32(1) - intersect + f32(y)
        plot(x, y - 1, brightness)
        if y < intersect:
            plot(x, y, f32(1) - brightness)
        intersect = intersect + gradient


@functools.lru_cache(maxsize=None)
def _resize_taps(src: int, dst: int, clamp_weights: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and 11-bit weights of OpenCV's bilinear filter along one axis (``src`` -> ``dst``)."""
    scale = 1.0 / (dst / src)
    f = ((np.arange(dst, dtype=np.float64) + 0.5) * scale - 0.5).astype(np.float32)
    s = np.floor(f).astype(np.int64)
    f = f - s.astype(np.float32)
    if clamp_weights:   # columns: a tap outside the image takes the border pixel at full weight
        f[s < 0], s[s < 0] = 0, 0
        f[s >= src - 1], s[s >= src - 1] = 0, src - 1
    w0 = np.rint((np.float32(1) - f) * np.float32(2048)).astype(np.int32)
    w1 = np.rint(f * np.float32(2048)).astype(np.int32)
    return np.clip(s, 0, src - 1), np.clip(s + 1, 0, src - 1), w0, w1


def _bilinear(pixels, rows, left, right, cw0, cw1, rw0, rw1, width: int, height: int) -> np.ndarray:
    """OpenCV's fixed-point bilinear pass on ``pixels`` (H, W, C): ``rows`` are the top then bottom source row of
    each output row, ``left`` / ``right`` the source columns of each output column, with their 11-bit weights."""
    channels = pixels.shape[2]
    lanes = np.arange(channels)
    taps = pixels.reshape(pixels.shape[0], -1).take(rows, axis=0)
    horizontal = taps.take((left[:, None] * channels + lanes).ravel(), axis=1).astype(np.int32) * np.repeat(
        cw0, channels)[None, :]
    horizontal += taps.take((right[:, None] * channels + lanes).ravel(), axis=1).astype(np.int32) * np.repeat(
        cw1, channels)[None, :]
    horizontal >>= 4
    top, bottom = horizontal[:height], horizontal[height:]
    top *= rw0[:, None]
    top >>= 16
    bottom *= rw1[:, None]
    bottom >>= 16
    top += bottom
    top += 2
    top >>= 2
    return top.astype(np.uint8).reshape(height, width, channels)


def resize_linear(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``cv2.resize(image, (width, height))`` (INTER_LINEAR) of a uint8 (H, W, C) image, bit for bit."""
    h, w = image.shape[:2]
    c0, c1, cw0, cw1 = _resize_taps(w, width, True)
    r0, r1, rw0, rw1 = _resize_taps(h, height, False)
    return _bilinear(image, np.concatenate([r0, r1]), c0, c1, cw0, cw1, rw0, rw1, width, height)
