"""The one neighbour-shift helper (geoseg.pair_slices) and the segment interior built on it.

Both are checked against a pixel-by-pixel reference on random segmentations, so
the vectorised slicing is exactly the rule it stands for, borders included.
"""

from __future__ import annotations

import numpy as np
import pytest

from neurncd_ros.core.discovery.geoseg import pair_slices
from neurncd_ros.core.discovery.modulation import interior


def naive_interior(segments: np.ndarray, radius: int) -> np.ndarray:
    """A pixel is interior if every pixel up to ``radius`` away in the 4 axis directions
    lies inside the image and in its segment (-1 is no segment, never interior)."""
    h, w = segments.shape
    out = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            s = segments[y, x]
            if s < 0:
                continue
            ok = True
            for r in range(1, radius + 1):
                for dy, dx in ((r, 0), (-r, 0), (0, r), (0, -r)):
                    yy, xx = y + dy, x + dx
                    if not (0 <= yy < h and 0 <= xx < w) or segments[yy, xx] != s:
                        ok = False
            out[y, x] = ok
    return out


def blobby_segments(rng: np.random.Generator, h: int, w: int, n: int) -> np.ndarray:
    """Random segmentation: nearest of n random seeds (compact regions), some pixels -1."""
    ys, xs = np.mgrid[0:h, 0:w]
    cy, cx = rng.uniform(0, h, n), rng.uniform(0, w, n)
    d = (ys[..., None] - cy) ** 2 + (xs[..., None] - cx) ** 2
    seg = d.argmin(-1).astype(np.int32)
    seg[rng.random((h, w)) < 0.05] = -1
    return seg


@pytest.mark.parametrize("seed", range(6))
def test_interior_matches_the_pixel_rule_on_random_segmentations(seed):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(5, 40)), int(rng.integers(5, 40))
    seg = blobby_segments(rng, h, w, int(rng.integers(1, 12)))
    for radius in (0, 1, 2, 3, 5):
        got = interior(seg, radius)
        assert got.dtype == bool and got.shape == seg.shape
        np.testing.assert_array_equal(got, naive_interior(seg, radius), err_msg=f"r={radius}")
    assert interior(seg, 1).any() or (seg >= 0).sum() < 9


def test_interior_of_a_radius_beyond_the_image_is_empty():
    """A radius at or over the image size leaves no pixel with all its neighbours."""
    seg = np.zeros((4, 6), np.int32)
    for radius in (4, 6, 9):
        np.testing.assert_array_equal(interior(seg, radius), np.zeros_like(seg, bool))
    np.testing.assert_array_equal(interior(seg, 1), naive_interior(seg, 1))


@pytest.mark.parametrize("dy,dx", [(0, 1), (1, 0), (-2, 3), (3, -1), (-1, -4), (5, 0),
                                   (0, -7), (7, 7), (-9, 2)])
def test_pair_slices_pair_each_pixel_with_its_shifted_neighbour(dy, dx):
    h, w = 5, 7
    idx = np.arange(h * w).reshape(h, w)
    c, o = pair_slices(h, w, dy, dx)
    centre, neighbour = idx[c], idx[o]
    assert centre.shape == neighbour.shape
    # Every pixel whose neighbour at (dy, dx) is inside the image, once, and only those.
    expected = [(y, x) for y in range(h) for x in range(w)
                if 0 <= y + dy < h and 0 <= x + dx < w]
    assert centre.size == len(expected)
    np.testing.assert_array_equal(np.sort(centre.ravel()),
                                  sorted(y * w + x for y, x in expected))
    np.testing.assert_array_equal(neighbour, centre + dy * w + dx)
