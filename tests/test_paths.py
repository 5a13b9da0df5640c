"""Geometry of the waypoint paths in selfid_jax.control.paths."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.control import paths

# float32 outputs when x64 is off; distances are O(0.1 m).
TOL = 1e-6


def _np(x):
    return np.asarray(x, dtype=np.float64)


def _with_start(offsets):
    """Vertices including the start (origin) in front."""
    o = _np(offsets)
    return np.concatenate([np.zeros((1, o.shape[1])), o], axis=0)


# ----------------------------------------------------------------------------
# star
# ----------------------------------------------------------------------------


def test_star_shape_and_closure():
    s = _np(paths.star())
    assert s.shape == (10, 3)
    np.testing.assert_allclose(s[-1], 0.0, atol=TOL)
    assert np.linalg.norm(s[0]) > 0.01  # the start is not waypoint 0
    assert np.all(np.isfinite(s))


@pytest.mark.parametrize("size,ratio", [(0.1, paths.PENTAGRAM_INNER_RATIO), (0.05, 0.5), (0.2, 0.3)])
def test_star_radii_and_equal_edges(size, ratio):
    v = _with_start(paths.star(size=size, dim=2, inner_ratio=ratio))[:10]  # vertices 0..9
    outer, inner = v[0::2], v[1::2]
    centre = outer.mean(axis=0)
    np.testing.assert_allclose(centre, [0.0, -size], atol=TOL)
    np.testing.assert_allclose(np.linalg.norm(outer - centre, axis=1), size, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(inner - centre, axis=1), ratio * size, rtol=1e-5)
    # 10 vertices 36 degrees apart, counter-clockwise
    ang = np.unwrap(np.arctan2(*(v - centre)[:, ::-1].T))
    np.testing.assert_allclose(np.diff(ang), np.pi / 5, atol=1e-5)
    closed = np.concatenate([v, v[:1]], axis=0)
    edges = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    np.testing.assert_allclose(edges, edges[0], rtol=1e-5)
    assert len(np.unique(np.round(v, 9), axis=0)) == 10


def test_star_default_ratio_is_regular_pentagram():
    assert paths.PENTAGRAM_INNER_RATIO == pytest.approx((3 - math.sqrt(5)) / 2)
    v = _with_start(paths.star(dim=2))
    # outer 0, inner 1, inner 3 and outer 4 lie on one line of the pentagram
    for a, b, c, d in [(0, 1, 3, 4), (2, 3, 5, 6), (8, 9, 1, 2)]:
        for p in (v[b], v[c]):
            u, w = v[d] - v[a], p - v[a]
            assert abs(u[0] * w[1] - u[1] * w[0]) < 1e-7


@pytest.mark.parametrize("plane,axes", [("xy", (0, 1)), ("xz", (0, 2)), ("yz", (1, 2))])
def test_star_planes(plane, axes):
    ref = _np(paths.star(dim=2))
    s = _np(paths.star(plane=plane, dim=3))
    np.testing.assert_allclose(s[:, axes], ref, atol=TOL)
    other = ({0, 1, 2} - set(axes)).pop()
    np.testing.assert_allclose(s[:, other], 0.0)


def test_star_dim6_zero_rotation():
    s6 = _np(paths.star(plane="yz", dim=6))
    assert s6.shape == (10, 6)
    np.testing.assert_allclose(s6[:, :3], _np(paths.star(plane="yz")), atol=TOL)
    np.testing.assert_array_equal(s6[:, 3:], 0.0)


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"size": 0.0}, "size"),
        ({"size": -1.0}, "size"),
        ({"size": float("nan")}, "size"),
        ({"plane": "zx"}, "plane"),
        ({"plane": "xz", "dim": 2}, "plane"),
        ({"dim": 4}, "dim"),
        ({"dim": 3.0}, "dim"),
        ({"inner_ratio": 1.2}, "inner_ratio"),
        ({"inner_ratio": 0.0}, "inner_ratio"),
    ],
)
def test_star_bad_args(kwargs, name):
    with pytest.raises(ValueError, match=name):
        paths.star(**kwargs)


# ----------------------------------------------------------------------------
# text
# ----------------------------------------------------------------------------


def test_font_glyphs_inside_cells():
    for char, (width, strokes) in paths.FONT.items():
        for stroke in strokes:
            pts = np.asarray(stroke, dtype=float)
            assert pts.ndim == 2 and pts.shape[1] == 2, char
            assert np.all(pts >= 0) and np.all(pts[:, 0] <= width), char
            assert np.all(pts[:, 1] <= paths.FONT_CAP_UNITS), char
    assert set("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789") <= set(paths.supported_characters())


@pytest.mark.parametrize("string", ["GRABLAB", "E", "ABCDEFGHIJKLMNOPQRSTUVWXYZ", "0123456789", "SELF-ID 2"])
def test_text_within_box(string):
    h = 0.012
    w = _np(paths.text(string, height=h, dim=2))
    box = paths.text_box(string, height=h)
    uv = _with_start(w) - box.origin
    assert np.all(uv[:, 0] >= -TOL) and np.all(uv[:, 0] <= box.width + TOL)
    assert np.all(uv[:, 1] >= -TOL) and np.all(uv[:, 1] <= h + TOL)
    # the box is actually used: the letters reach its edges
    assert uv[:, 0].min() < TOL and uv[:, 0].max() > box.width - TOL
    assert uv[:, 1].min() < TOL and uv[:, 1].max() > h - TOL
    # no zero-length moves, the start is not a waypoint
    assert np.all(np.linalg.norm(np.diff(_with_start(w), axis=0), axis=1) > 1e-6)


def test_text_grablab():
    w = _np(paths.text("GRABLAB"))
    assert w.shape[1] == 3
    assert 40 <= w.shape[0] <= 120
    np.testing.assert_allclose(w[:, 2], 0.0)
    box = paths.text_box("GRABLAB")
    assert box.width == pytest.approx(7 * 0.008 + 6 * 0.003)  # 7 letters 4/6*h wide, h/4 gaps
    length = paths.path_length(w)
    assert 0.2 < length < 1.0


def test_text_exact_letter_l_and_e():
    h = 0.012
    u = h / 6
    np.testing.assert_allclose(_np(paths.text("L", height=h, dim=2)), [[0, -h], [4 * u, -h]], atol=TOL)
    # E starts at its lower-left corner: spine, top bar, middle bar, bottom bar (retracing)
    e = _np(paths.text("E", height=h, dim=2))
    expected = [[0, h], [4 * u, h], [0, h], [0, h / 2], [3 * u, h / 2], [0, h / 2], [0, 0], [4 * u, 0]]
    np.testing.assert_allclose(e, expected, atol=TOL)


def test_text_letters_left_to_right_and_spacing():
    h, gap = 0.01, 0.004
    one = _np(paths.text("L", height=h, spacing=gap, dim=2))
    two = _np(paths.text("LL", height=h, spacing=gap, dim=2))
    # second L is the first shifted right by its width plus the gap
    np.testing.assert_allclose(two[:2], one, atol=TOL)
    np.testing.assert_allclose(two[2:], _with_start(one) + [4 * h / 6 + gap, 0], atol=TOL)
    assert paths.text_box("LL", height=h, spacing=gap).width == pytest.approx(2 * 4 * h / 6 + gap)


@pytest.mark.parametrize("plane,axes", [("xy", (0, 1)), ("xz", (0, 2)), ("yz", (1, 2))])
def test_text_planes_and_dim6(plane, axes):
    ref = _np(paths.text("AB", dim=2))
    t = _np(paths.text("AB", plane=plane, dim=6))
    assert t.shape == (ref.shape[0], 6)
    np.testing.assert_allclose(t[:, axes], ref, atol=TOL)
    np.testing.assert_array_equal(np.delete(t, axes, axis=1), 0.0)


def test_text_unknown_character():
    with pytest.raises(ValueError, match=r"'a'.*supported characters: 'ABC"):
        paths.text("GRaB")
    with pytest.raises(ValueError, match=r"'\?'"):
        paths.text("?")
    with pytest.raises(ValueError, match="string"):
        paths.text("")
    with pytest.raises(ValueError, match="height"):
        paths.text("A", height=0)
    with pytest.raises(ValueError, match="spacing"):
        paths.text("A", spacing=-1.0)
    with pytest.raises(ValueError, match="plane"):
        paths.text("A", plane="xz", dim=2)


# ----------------------------------------------------------------------------
# cube
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("edge", [0.15, 0.05])
def test_cube_covers_all_edges(edge):
    c = _np(paths.cube(edge=edge))
    assert c.shape == (16, 3)  # 12 edges + 4 repeats: the Chinese-postman minimum
    np.testing.assert_allclose(c[-1], 0.0, atol=TOL)
    v = _with_start(c)
    seg = np.diff(v, axis=0)
    np.testing.assert_allclose(np.linalg.norm(seg, axis=1), edge, rtol=1e-5)
    corners = np.round(v / edge).astype(int)
    np.testing.assert_allclose(corners * edge, v, atol=TOL)  # every waypoint is a corner
    assert corners.min() == 0 and corners.max() == 1
    visited = {frozenset((tuple(a), tuple(b))) for a, b in zip(corners[:-1], corners[1:])}
    cube_edges = {
        frozenset((a, b))
        for a, b in itertools.combinations(itertools.product((0, 1), repeat=3), 2)
        if sum(abs(x - y) for x, y in zip(a, b)) == 1
    }
    assert len(cube_edges) == 12
    assert visited == cube_edges
    assert paths.path_length(c) == pytest.approx(16 * edge, rel=1e-5)


def test_cube_dim6_and_bad_args():
    c6 = _np(paths.cube(dim=6))
    assert c6.shape == (16, 6)
    np.testing.assert_array_equal(c6[:, 3:], 0.0)
    for kwargs, name in [({"edge": 0}, "edge"), ({"dim": 2}, "dim"), ({"dim": 5}, "dim")]:
        with pytest.raises(ValueError, match=name):
            paths.cube(**kwargs)


# ----------------------------------------------------------------------------
# rotation
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("axis,angle,steps", [((1, 0, 0), 0.2, 1), ((0, 2, 2), 0.5, 4), ((0, 0, -3), -0.3, 3)])
def test_rotation_offsets(axis, angle, steps):
    r = _np(paths.rotation(axis=axis, angle=angle, steps=steps))
    assert r.shape == (steps, 6)
    np.testing.assert_array_equal(r[:, :3], 0.0)
    k = np.arange(1, steps + 1)
    np.testing.assert_allclose(np.linalg.norm(r[:, 3:], axis=1), abs(angle) * k / steps, rtol=1e-5)
    unit = np.asarray(axis, float) / np.linalg.norm(axis)
    np.testing.assert_allclose(r[-1, 3:], unit * angle, atol=TOL)


@pytest.mark.parametrize(
    "kwargs,name",
    [({"dim": 3}, "dim"), ({"axis": (0, 0, 0)}, "axis"), ({"axis": (1, 0)}, "axis"), ({"steps": 0}, "steps")],
)
def test_rotation_bad_args(kwargs, name):
    with pytest.raises(ValueError, match=name):
        paths.rotation(**kwargs)


# ----------------------------------------------------------------------------
# place, path_length, densify
# ----------------------------------------------------------------------------


def test_place_positions_and_jit():
    off = paths.star(dim=3)
    start = jnp.array([0.4, -0.1, 0.3])
    placed = jax.jit(paths.place)(off, start)
    np.testing.assert_allclose(_np(placed), _np(off) + _np(start), atol=TOL)
    # batched starts broadcast over the waypoint axis
    starts = jnp.stack([start, 2 * start])
    assert paths.place(off, starts).shape == (2, 10, 3)


def test_place_dim6_keeps_relative_rotation():
    off = paths.rotation(axis=(0, 0, 1), angle=0.3, steps=2)
    start = jnp.array([0.4, -0.1, 0.3, 0.1, 0.2, 0.3])
    placed = _np(paths.place(off, start))
    np.testing.assert_allclose(placed[:, :3], np.tile(_np(start)[:3], (2, 1)), atol=TOL)
    np.testing.assert_allclose(placed[:, 3:], _np(off)[:, 3:], atol=TOL)
    with pytest.raises(ValueError, match="start_task_vector"):
        paths.place(off, start[:3])


def test_path_length_star():
    size = 0.1
    s = paths.star(size=size)
    edge = np.linalg.norm(_np(s)[0])
    assert paths.path_length(s) == pytest.approx(10 * edge, rel=1e-5)
    # from a different start only the first move changes
    start = np.array([0.0, 0.0, 0.1])
    assert paths.path_length(s, start) == pytest.approx(9 * edge + np.hypot(edge, 0.1), rel=1e-5)


def test_densify():
    c = paths.cube(edge=0.15)
    d = _np(paths.densify(c, 0.04))
    assert d.shape == (16 * 4, 3)  # ceil(0.15 / 0.04) = 4 pieces per edge
    steps = np.linalg.norm(np.diff(_with_start(d), axis=0), axis=1)
    assert steps.max() <= 0.04 + TOL
    np.testing.assert_allclose(d[3::4], _np(c), atol=TOL)  # originals kept
    assert paths.path_length(d) == pytest.approx(paths.path_length(c), rel=1e-5)
    # exact multiple: no extra points
    assert paths.densify(c, 0.15).shape == (16, 3)
    # rotation steps bounded by max_angle
    r = paths.rotation(angle=0.5, steps=1)
    assert paths.densify(r, 0.01, max_angle=0.1).shape == (5, 6)
    assert paths.densify(r, 0.01).shape == (1, 6)
    with pytest.raises(ValueError, match="max_segment"):
        paths.densify(c, 0.0)
