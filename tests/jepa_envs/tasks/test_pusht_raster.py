"""The raster rules of the standard PushT's frames (jepa_envs.tasks.pusht_raster) against their definitions.

Frame-for-frame agreement with gym-pusht itself is checked by ``make interop`` and, on recorded frames, by
test_pusht_standard.py; these tests pin each rule on its own.
"""
import math

import numpy as np
import pytest

from jepa_envs.tasks import pusht_raster as raster


def _bresenham_by_steps(x1, y1, x2, y2):
    """The textbook integer Bresenham walk (error term started at dx/2 or -dy/2), one point per step."""
    dx, dy = abs(x2 - x1), abs(y2 - y1)
    sx, sy = (1 if x1 < x2 else -1), (1 if y1 < y2 else -1)
    err = dx // 2 if dx > dy else -(dy // 2)
    points = []
    while (x1, y1) != (x2, y2):
        points.append((x1, y1))
        e2 = err
        if e2 > -dx:
            err -= dy
            x1 += sx
        if e2 < dy:
            err += dx
            y1 += sy
    return points + [(x2, y2)]


def test_closed_form_bresenham_equals_the_step_by_step_walk():
    rng = np.random.default_rng(0)
    lines = [(0, 0, dx, dy) for dx in range(-13, 14) for dy in range(-13, 14)]
    lines += [tuple(int(v) for v in rng.integers(-40, 560, 4)) for _ in range(300)]
    index, xs, ys = raster.bresenham(np.array(lines))
    for i, line in enumerate(lines):
        assert list(zip(xs[index == i], ys[index == i])) == _bresenham_by_steps(*line), line


def test_thick_line_widens_across_the_minor_axis():
    rows, cols, _ = raster.thick_line_pixels(np.array([[10, 20, 60, 30]]), 4, (512, 512))   # mostly horizontal
    for x in range(10, 61):
        column = sorted(rows[cols == x])
        assert len(column) == 4 and column == list(range(column[0], column[0] + 4))
    rows, cols, _ = raster.thick_line_pixels(np.array([[10, 20, 14, 90]]), 4, (512, 512))   # mostly vertical
    for y in range(20, 91):
        row = sorted(cols[rows == y])
        assert len(row) == 4 and row == list(range(row[0], row[0] + 4))
    with pytest.raises(ValueError, match="width >= 2"):
        raster.thick_line_pixels(np.array([[0, 0, 5, 5]]), 1, (512, 512))


def test_a_line_leaving_the_canvas_keeps_its_error_term_from_the_clipped_start():
    # entirely inside, the clipped walk is the closed form
    inside = raster._clipped_walk(3, 4, 90, 40, 512, 512, np.arange(-1, 3))
    assert inside == _bresenham_by_steps(3, 4, 90, 40)
    # crossing the bottom edge: starts at the clipped start, error term of the whole segment
    x1, y1, x2, y2 = 100, 480, 140, 560
    cx, cy, _, _ = raster.clip_segment(x1, y1, x2, y2, 512, 512)
    walk = raster._clipped_walk(x1, y1, x2, y2, 512, 512, np.arange(-1, 3))
    assert walk[0] == (cx, cy) == (100, 480)
    assert max(y for _, y in walk) == 512   # the clipped end (the canvas' edge counts as inside for clipping)
    assert raster.clip_segment(-50, -50, -10, -5, 512, 512) is None


def _pixels(spans):
    rows, lo, hi = spans
    return {(int(r), int(c)) for r, a, b in zip(rows, lo, hi) for c in range(a, b + 1)}


def test_polygon_fill_of_a_rectangle_covers_its_corners_inclusive():
    spans, which = raster.polygon_spans([([10, 20, 20, 10], [5, 5, 9, 9])])
    assert _pixels(spans) == {(r, c) for r in range(5, 10) for c in range(10, 21)}
    assert set(which.tolist()) == {0}


def test_polygon_fill_lies_between_the_inner_and_outer_shell_of_the_polygon():
    rng = np.random.default_rng(1)
    for _ in range(30):
        cx, cy, r = rng.uniform(50, 450, 2).tolist() + [rng.uniform(5, 60)]
        angles = np.sort(rng.uniform(0, 2 * np.pi, 5))
        xs = np.round(cx + r * np.cos(angles)).astype(int)
        ys = np.round(cy + r * np.sin(angles)).astype(int)
        filled = _pixels(raster.polygon_spans([(xs, ys)])[0])
        poly = np.stack([xs, ys], 1).astype(float)

        def signed(p):   # min signed distance of p to the edges' lines (convex polygon, counter-clockwise)
            d = []
            for a, b in zip(poly, np.roll(poly, -1, 0)):
                e = b - a
                if np.hypot(*e) == 0:
                    continue
                d.append((e[0] * (p[1] - a[1]) - e[1] * (p[0] - a[0])) / np.hypot(*e))
            return min(d)

        for y in range(ys.min() - 2, ys.max() + 3):
            for x in range(xs.min() - 2, xs.max() + 3):
                s = signed((x, y))
                if s > 1.0:
                    assert (y, x) in filled, "a pixel a full pixel inside is filled"
                if s < -1.0:
                    assert (y, x) not in filled, "a pixel a full pixel outside is not filled"


def test_filled_circle_is_2r_across_and_symmetric():
    for radius in (1, 2, 11, 15, 40):
        pixels = _pixels(raster.circle_spans(100, 200, radius))
        middle = sorted(c for r, c in pixels if r == 200)
        assert middle == list(range(100 - radius, 100 + radius))
        for r, c in pixels:
            assert (2 * 200 - 1 - r, c) in pixels and (r, 2 * 100 - 1 - c) in pixels   # about (99.5, 199.5)
            assert math.hypot(c + 0.5 - 100, r + 0.5 - 200) <= radius + 1
    assert not _pixels(raster.circle_spans(5, 5, 0))


def test_canvas_keeping_the_sampled_pixels_resizes_like_the_full_canvas():
    rng = np.random.default_rng(2)
    background = rng.integers(0, 256, (512, 512, 3), dtype=np.uint8)
    full = raster.Canvas(background)
    sampled = raster.Canvas.for_resize(background, 96, 96)
    assert len(sampled.rows) < 200 and len(sampled.cols) < 200
    spans, _ = raster.polygon_spans([([30, 400, 300], [20, 100, 480])])
    for canvas in (full, sampled):
        canvas.paint_spans(spans, (10, 200, 30))
        canvas.paint_pixels(np.arange(512), np.arange(512), (255, 0, 0))
        raster.aaline(canvas, 40, 500, 470, 30, (231, 76, 60))
    np.testing.assert_array_equal(sampled.resize(96, 96), full.resize(96, 96))
    np.testing.assert_array_equal(full.resize(96, 96), raster.resize_linear(full.pixels, 96, 96))
    with pytest.raises(ValueError, match="does not keep every pixel"):
        sampled.resize(200, 200)


def test_resize_is_exact_on_constants_and_close_to_bilinear_interpolation():
    flat = np.full((512, 512, 3), 77, np.uint8)
    assert (raster.resize_linear(flat, 96, 96) == 77).all()
    assert (raster.resize_linear(flat, 680, 680) == 77).all()
    ramp = np.repeat(np.repeat(np.linspace(0, 255, 512)[None, :, None], 512, 0), 3, 2).round().astype(np.uint8)
    out = raster.resize_linear(ramp, 96, 96)[0, :, 0].astype(float)
    src = np.clip((np.arange(96) + 0.5) * 512 / 96 - 0.5, 0, 511)   # pixel-centre mapping
    expected = np.interp(src, np.arange(512), ramp[0, :, 0].astype(float))
    assert np.abs(out - expected).max() <= 1.0


def test_resize_matches_opencv_bit_for_bit_where_opencv_is_installed():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(3)
    for width, height in ((96, 96), (680, 680), (84, 64), (33, 97)):
        image = rng.integers(0, 256, (512, 512, 3), dtype=np.uint8)
        np.testing.assert_array_equal(raster.resize_linear(image, width, height), cv2.resize(image, (width, height)))


def test_aaline_blends_in_single_precision_and_draws_whole_pixels_on_axis_lines():
    canvas = raster.Canvas(np.full((20, 20, 3), 255, np.uint8))
    raster.aaline(canvas, 3, 5, 3, 12, (231, 76, 60))   # vertical, integer ends: full-brightness pixels
    column = canvas.pixels[:, 3]
    assert (column[5:13] == (231, 76, 60)).all() and (column[:5] == 255).all() and (column[13:] == 255).all()
    canvas = raster.Canvas(np.full((20, 20, 3), 255, np.uint8))
    raster.aaline(canvas, 2, 2, 10, 6, (0, 0, 0))   # slope 1/2: at x = 3 the line is half in rows 2 and 3
    b = np.float32(0.5)
    half = np.uint8(b * np.float32(0) + (np.float32(1) - b) * np.float32(255))
    assert canvas.pixels[2, 3, 0] == half == canvas.pixels[3, 3, 0] == 127
    assert canvas.pixels[3, 4, 0] == 0 and canvas.pixels[2, 4, 0] == 255 == canvas.pixels[4, 4, 0]   # on a row
    raster.aaline(canvas, -30, -30, -5, -2, (0, 0, 0))   # outside: nothing drawn, no error
