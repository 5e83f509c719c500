"""Mutation kills for pipeline/core/align.py (issue 11; tests/mutation/README.md, mut-align).

Every expectation is computed independently of the module: homographies applied by hand
with numpy, resizes checked against block means, the ECC correlation against a
zero-mean normalised cross-correlation written out in numpy, bilinear resampling by
hand, and the choice logic of ``estimate_alignment`` against what its docstring says,
with the estimators replaced by stubs that return chosen transforms.
"""

from __future__ import annotations

import itertools
import logging
import math

import cv2
import numpy as np
import pytest
from scipy import ndimage

from pipeline.core import align
from pipeline.core.align import (
    analytic_alignment,
    compose,
    estimate_alignment,
    map_points,
    rescale_homography,
    scale_of,
    warp,
)
from pipeline.errors import InputError

# --- independent helpers --------------------------------------------------------------------


def apply_h(h, xy) -> np.ndarray:
    """``h`` applied to points (n, 2) by hand: x' = (h00 x + h01 y + h02) / (h20 x + ...)."""
    xy = np.atleast_2d(np.asarray(xy, float))
    h = np.asarray(h, float)
    if h.shape == (2, 3):
        h = np.vstack([h, [0.0, 0.0, 1.0]])
    x, y = xy[:, 0], xy[:, 1]
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return np.c_[
        (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    ]


def resize_point(xy, from_shape, to_shape) -> np.ndarray:
    """Where a pixel position lands in a resized copy: pixel edges scale, centres at integers."""
    xy = np.atleast_2d(np.asarray(xy, float))
    sx = to_shape[1] / from_shape[1]
    sy = to_shape[0] / from_shape[0]
    return np.c_[(xy[:, 0] + 0.5) * sx - 0.5, (xy[:, 1] + 0.5) * sy - 0.5]


def texture(shape, seed=0, sigma=2.0) -> np.ndarray:
    """A smooth random, asymmetric, positive texture in [0.05, 1.05] (float32)."""
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.uniform(0, 1, shape), sigma)
    t = (t - t.min()) / np.ptp(t)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    t = t + 0.2 * xx / shape[1] + 0.1 * (yy / shape[0]) ** 2  # no symmetry
    return (0.05 + t / t.max()).astype(np.float32)


def block_mean(img: np.ndarray, f: int) -> np.ndarray:
    r, c = img.shape[0] // f, img.shape[1] // f
    return img[: r * f, : c * f].reshape(r, f, c, f).mean(axis=(1, 3))


def ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Zero-mean normalised cross-correlation of ``a`` and ``b`` over ``mask``."""
    x = a[mask].astype(float)
    y = b[mask].astype(float)
    x -= x.mean()
    y -= y.mean()
    return float((x * y).sum() / math.sqrt((x * x).sum() * (y * y).sum()))


# --- homography helpers ---------------------------------------------------------------------


def test_a_2x3_affine_is_completed_with_the_bottom_row_0_0_1():
    a = np.array([[1.1, 0.2, 5.0], [-0.1, 0.9, -3.0]])
    pts = np.array([[0.0, 0.0], [10.0, 4.0], [-7.0, 30.0]])
    np.testing.assert_allclose(map_points(a, pts), apply_h(a, pts), rtol=1e-13, atol=1e-12)
    assert scale_of(a) == pytest.approx(math.sqrt(1.1 * 0.9 + 0.2 * 0.1), rel=1e-13)
    full = compose(a)
    np.testing.assert_array_equal(full[2], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(full[:2], a, rtol=1e-15)


def test_a_homography_not_normalised_acts_the_same_and_is_returned_normalised():
    h = np.array([[1.02, 0.01, 3.0], [-0.02, 0.97, -4.0], [2e-5, -1e-5, 1.0]])
    pts = np.array([[0.0, 0.0], [640.0, 0.0], [0.0, 480.0], [320.0, 240.0]])
    for k in (2.5, -0.5):
        np.testing.assert_allclose(map_points(k * h, pts), apply_h(h, pts), rtol=1e-12)
        assert scale_of(k * h) == pytest.approx(math.sqrt(1.02 * 0.97 + 0.01 * 0.02), rel=1e-12)
        c = compose(k * h, np.eye(3))
        np.testing.assert_allclose(c, h, rtol=1e-13, atol=1e-18)
        assert c[2, 2] == 1.0
    # the product is taken before it is normalised: h2 applied first, then h1
    h1 = np.array([[2.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    h2 = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.001, 0.0, 2.0]])
    p = np.array([[10.0, 20.0]])
    np.testing.assert_allclose(map_points(compose(h1, h2), p), apply_h(h1, apply_h(h2, p)))
    np.testing.assert_allclose(
        map_points(compose(h1, h2, h1), p), apply_h(h1, apply_h(h2, apply_h(h1, p)))
    )
    assert compose(h1, h2)[2, 2] == 1.0


def test_singular_means_a_determinant_below_1e_12_after_normalising():
    assert scale_of(np.diag([1e-6, 2e-6, 1.0])) == pytest.approx(math.sqrt(2e-12))  # det 2e-12
    with pytest.raises(InputError, match="singular"):
        scale_of(np.diag([1e-6, 0.5e-6, 1.0]))  # det 5e-13
    # 10 * diag(1e-6, 2e-6, 1): the raw matrix's det is 2e-9, the normalised one's 2e-12
    assert scale_of(10 * np.diag([1e-6, 2e-6, 1.0])) == pytest.approx(math.sqrt(2e-12))
    with pytest.raises(InputError, match="singular"):
        scale_of(1e3 * np.diag([1e-6, 0.5e-6, 1.0]))  # raw det 5e-4, normalised 5e-13
    with pytest.raises(InputError, match=r"3x3 \(or 2x3 affine\)"):
        scale_of(np.eye(4))
    with pytest.raises(InputError, match=r"finite with h\[2, 2\] != 0"):
        scale_of(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, np.inf]]))
    with pytest.raises(InputError, match=r"homographies\[1\]"):
        compose(np.eye(3), np.zeros((3, 3)))
    with pytest.raises(InputError, match="at least one"):
        compose()


def test_map_points_keeps_any_leading_shape_and_refuses_other_last_axes():
    h = np.array([[1.02, 0.01, 3.0], [-0.02, 0.97, -4.0], [2e-5, -1e-5, 1.0]])
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 500, (3, 4, 2))
    out = map_points(h, p)
    assert out.shape == (3, 4, 2) and out.dtype == np.float64
    np.testing.assert_allclose(out.reshape(-1, 2), apply_h(h, p.reshape(-1, 2)), rtol=1e-13)
    one = map_points(h, [7.0, 9.0])
    assert one.shape == (2,)
    np.testing.assert_allclose(one, apply_h(h, [[7.0, 9.0]])[0], rtol=1e-13)
    for bad in (np.zeros((5, 3)), np.zeros(3), np.zeros((2, 1))):
        with pytest.raises(InputError, match=r"points_xy must have shape \(\.\.\., 2\)"):
            map_points(h, bad)


@pytest.mark.parametrize(("big", "small"), [((600, 800), (150, 400)), ((173, 231), (600, 500))])
def test_rescale_homography_commutes_with_the_resize(big, small):
    h = np.array([[1.03, 0.02, -7.0], [-0.01, 0.96, 5.0], [3e-5, -2e-5, 1.0]])
    r = rescale_homography(h, big, small)
    assert r[2, 2] == 1.0
    pts = np.array([[0.0, 0.0], [big[1] - 1.0, 0.0], [13.3, big[0] - 1.0], [100.7, 55.2]])
    # a point mapped by h and then resized = the point resized and then mapped by r
    np.testing.assert_allclose(
        apply_h(r, resize_point(pts, big, small)),
        resize_point(apply_h(h, pts), big, small),
        rtol=1e-10,
        atol=1e-9,
    )


# --- frames and matching copies -------------------------------------------------------------


@pytest.mark.parametrize(
    ("bad", "what"),
    [
        (np.zeros(5, np.float32), "non-empty numeric"),
        (np.zeros((2, 2, 2, 2), np.float32), "non-empty numeric"),
        (np.zeros((0, 5), np.float32), "non-empty numeric"),
        (np.zeros((5, 5), bool), "non-empty numeric"),
        (np.full((5, 5), "a"), "non-empty numeric"),
        (np.zeros((5, 5), np.complex64), "real-valued"),
    ],
)
def test_frames_that_cannot_be_images_are_refused_by_name(bad, what):
    with pytest.raises(InputError, match=what):
        warp(bad, np.eye(3), (5, 5))
    with pytest.raises(InputError, match=rf"frames\[1\] .*{what}"):
        estimate_alignment([np.ones((200, 200), np.float32), bad])


def test_grey_weights_rgb_like_rec601_and_averages_other_channel_counts():
    rng = np.random.default_rng(4)
    rgb = rng.random((7, 9, 3))
    g = align._grey(rgb)
    assert g.dtype == np.float32 and g.shape == (7, 9)
    np.testing.assert_allclose(g, rgb @ [0.299, 0.587, 0.114], rtol=1e-5, atol=1e-6)
    for channels in (1, 2, 4, 5):
        x = rng.random((6, 8, channels)).astype(np.float32)
        g = align._grey(x)
        assert g.dtype == np.float32 and g.shape == (6, 8)
        np.testing.assert_allclose(g, x.astype(float).mean(axis=2), rtol=1e-6)
    flat = rng.random((6, 8))
    np.testing.assert_array_equal(align._grey(flat), flat.astype(np.float32))


def test_matching_copy_is_the_area_mean_down_to_max_side():
    rng = np.random.default_rng(5)
    for shape, max_side, expect in (
        ((1000, 500), 200, (200, 100)),
        ((500, 1000), 200, (100, 200)),
        ((600, 900), 300, (200, 300)),
    ):
        img = rng.random(shape).astype(np.float32)
        m = align._matching_image(img, max_side)
        assert m.shape == expect and m.dtype == np.float32
        np.testing.assert_allclose(m, block_mean(img, shape[0] // expect[0]), rtol=1e-5)
    img = rng.random((300, 200)).astype(np.float32)
    np.testing.assert_array_equal(align._matching_image(img, 300), img)  # s == 1: unchanged
    np.testing.assert_array_equal(align._matching_image(img, 600), img)  # never enlarged
    thin = rng.random((1000, 3)).astype(np.float32)  # 3 * 0.2 rounds to 1 column
    m = align._matching_image(thin, 200)
    assert m.shape == (200, 1)
    np.testing.assert_allclose(m[:, 0], thin.reshape(200, 5, 3).mean(axis=(1, 2)), rtol=1e-5)
    thin = rng.random((2, 1000)).astype(np.float32)  # 2 * 0.2 rounds to 0: kept at 1 row
    assert align._matching_image(thin, 200).shape == (1, 200)


@pytest.mark.parametrize(
    ("shape", "sides"),
    [
        ((768, 1024), [(96, 128), (192, 256), (384, 512), (768, 1024)]),
        ((192, 300), [(96, 150), (192, 300)]),
        ((191, 300), [(191, 300)]),
        ((400, 194), [(200, 97), (400, 194)]),  # 194 // 2 = 97 >= 96, then 97 // 2 = 48
    ],
)
def test_pyramid_halves_by_area_means_until_the_short_side_would_drop_below_96(shape, sides):
    img = texture(shape, seed=6)
    levels = align._pyramid(img)
    assert [lv.shape for lv in levels] == sides
    assert levels[-1] is img
    for coarse, fine in itertools.pairwise(levels):
        if fine.shape[0] % 2 == 0 and fine.shape[1] % 2 == 0:
            np.testing.assert_allclose(coarse, block_mean(fine, 2), rtol=1e-5, atol=1e-7)


def test_textureless_means_std_at_most_1e_5_of_the_mean_level():
    rng = np.random.default_rng(7)
    assert align._is_textureless(np.zeros((10, 10), np.float32))
    assert align._is_textureless(np.full((10, 10), -3.0, np.float32))
    noise = rng.standard_normal((100, 100))
    noise /= noise.std()
    for level in (1.0, -2.0, 100.0):
        assert align._is_textureless((level + 0.9e-5 * abs(level) * noise).astype(np.float64))
        assert not align._is_textureless((level + 1.1e-5 * abs(level) * noise).astype(np.float64))


def test_project_constrains_to_each_model():
    w = np.array([[2.1, 0.04, 6.0], [-0.02, 1.9, -4.0], [2e-4, -1e-4, 2.0]])
    np.testing.assert_allclose(align._project(w, "homography", (300, 400)), w / 2, rtol=1e-15)
    aff = align._project(w, "affine", (300, 400))
    np.testing.assert_allclose(aff, [[1.05, 0.02, 3.0], [-0.01, 0.95, -2.0], [0, 0, 1]], rtol=1e-14)
    # similarity of a rotation by 30 degrees and scaling 1.1 about (50, 20) plus a shear
    c, s = 1.1 * math.cos(math.pi / 6), 1.1 * math.sin(math.pi / 6)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0, 0, 1.0]])
    shear = np.array([[1.0, 0.03, 0.0], [0.0, 1.0, 0.0], [0, 0, 1.0]])
    m = rot @ shear
    m[:2, 2] = [4.0, -6.0]
    for shape in ((300, 400), (401, 120)):
        sim = align._project(3.0 * m, "similarity", shape)
        centre = [[(shape[1] - 1) / 2, (shape[0] - 1) / 2]]
        np.testing.assert_allclose(apply_h(sim, centre), apply_h(m, centre), atol=1e-9)
        a_, b_ = (m[0, 0] + m[1, 1]) / 2, (m[1, 0] - m[0, 1]) / 2
        np.testing.assert_allclose(sim[:2, :2], [[a_, -b_], [b_, a_]], rtol=1e-14)
        np.testing.assert_array_equal(sim[2], [0.0, 0.0, 1.0])
        # a similarity is a rotation by atan2(b, a), close to 30 degrees here
        assert math.degrees(math.atan2(b_, a_)) == pytest.approx(30.0, abs=1.0)


# --- correlation on the overlap -------------------------------------------------------------


def test_correlation_is_the_zero_mean_ncc_on_the_overlap():
    img = texture((120, 160), seed=8)
    # the template shows the image shifted: template(x, y) = image(x + 7, y - 4)
    template = np.zeros_like(img)
    template[4:, :-7] = img[:-4, 7:]
    rng = np.random.default_rng(9)
    template = template + 0.05 * rng.standard_normal(template.shape).astype(np.float32)
    w = np.array([[1.0, 0, 7.0], [0, 1.0, -4.0], [0, 0, 1.0]])  # template x -> image x + 7
    mask = np.zeros(img.shape, bool)
    mask[4:, :-7] = True
    got = align._correlation(template, img, w)
    assert got == pytest.approx(ncc(template, np.roll(np.roll(img, 4, 0), -7, 1), mask), abs=1e-4)
    assert 0.9 < got < 1.0
    # no shift: the whole template overlaps, a wrong warp correlates less
    assert align._correlation(img, img, np.eye(3)) == pytest.approx(1.0, abs=1e-6)
    assert align._correlation(template, img, np.eye(3)) < got - 0.2


def test_correlation_needs_a_quarter_of_the_template_overlapped():
    img = texture((100, 160), seed=10)
    for shift, enough in ((120.0, True), (121.0, False), (-120.0, True), (-121.0, False)):
        w = np.array([[1.0, 0, shift], [0, 1.0, 0.0], [0, 0, 1.0]])  # overlap 160 - |shift|
        got = align._correlation(img, img, w)
        if enough:  # 40 of 160 columns: exactly a quarter
            assert got != -1.0 and -1.0 < got < 1.0
        else:
            assert got == -1.0


# --- features -------------------------------------------------------------------------------


def _keypoints(pts):
    return [cv2.KeyPoint(float(x), float(y), 3.0) for x, y in pts]


_TRUE = {
    "homography": np.array([[1.02, 0.01, 5.0], [-0.01, 0.99, -3.0], [1e-5, -2e-5, 1.0]]),
    "affine": np.array([[1.02, 0.03, 5.0], [-0.01, 0.99, -3.0], [0.0, 0.0, 1.0]]),
    "similarity": np.array(
        [
            [1.02 * math.cos(0.05), -1.02 * math.sin(0.05), 5.0],
            [1.02 * math.sin(0.05), 1.02 * math.cos(0.05), -3.0],
            [0.0, 0.0, 1.0],
        ]
    ),
}


def _matches(model, n=40, seed=1, displaced=(), disp=0.0):
    """Keypoints of ``n`` points and their images under the model's true map; descriptors
    identical (integers, so distances are exact); the ``displaced`` ones moved ``disp`` px."""
    rng = np.random.default_rng(seed)
    pa = rng.uniform(10, 290, (n, 2))
    pb = apply_h(_TRUE[model], pa)
    pb[list(displaced)] += disp / math.sqrt(2)
    da = rng.integers(0, 100, (n, 128)).astype(np.float32)
    return (_keypoints(pa), da), (_keypoints(pb), da.copy())


def _map_error(w, h) -> float:
    test = np.random.default_rng(0).uniform(0, 300, (50, 2))
    return float(np.abs(apply_h(w, test) - apply_h(h, test)).max())


@pytest.mark.parametrize("model", ["homography", "affine", "similarity"])
def test_feature_warp_fits_the_model_and_its_ransac_threshold_is_1_5_px(model):
    fa, fb = _matches(model)
    w = align._feature_warp(fa, fb, model)
    assert w.shape == (3, 3) and w[2, 2] == 1.0
    assert _map_error(w, _TRUE[model]) < 1e-3  # keypoint positions are float32
    if model != "homography":
        np.testing.assert_array_equal(w[2], [0.0, 0.0, 1.0])
    # 10 of 40 matches 1.2 px off are inliers and pull the fit; 2 px off are rejected
    w = align._feature_warp(*_matches(model, displaced=range(30, 40), disp=1.2), model)
    assert _map_error(w, _TRUE[model]) > 0.05
    w = align._feature_warp(*_matches(model, displaced=range(30, 40), disp=2.0), model)
    assert _map_error(w, _TRUE[model]) < 1e-3


def test_feature_warp_similarity_of_a_sheared_map_is_a_rotation_and_scale():
    fa, fb = _matches("affine")
    w = align._feature_warp(fa, fb, "similarity")
    assert w[0, 0] == pytest.approx(w[1, 1], abs=1e-9)
    assert w[0, 1] == pytest.approx(-w[1, 0], abs=1e-9)
    assert _map_error(w, _TRUE["affine"]) > 0.5


def test_feature_warp_needs_8_features_8_matches_and_8_inliers():
    (ka, da), (kb, db) = _matches("affine", n=12)
    w = align._feature_warp((ka[:8], da[:8]), (kb[:8], db[:8]), "affine")
    assert _map_error(w, _TRUE["affine"]) < 1e-3
    for a, b in (
        ((ka[:7], da[:7]), (kb, db)),
        ((ka, da), (kb[:7], db[:7])),
        ((ka, None), (kb, db)),
        ((ka, da), (kb, None)),
    ):
        with pytest.raises(align._EstimationError, match="too few features"):
            align._feature_warp(a, b, "affine")
    # 8 exact matches among 12 (4 far off): 8 inliers are enough, 7 of 12 are not
    for model in ("homography", "affine", "similarity"):
        (ka, da), (kb, db) = _matches(model, n=12, displaced=range(8, 12), disp=40.0)
        assert _map_error(align._feature_warp((ka, da), (kb, db), model), _TRUE[model]) < 1e-3
        (ka, da), (kb, db) = _matches(model, n=12, displaced=range(7, 12), disp=40.0)
        with pytest.raises(align._EstimationError, match="no consistent transform"):
            align._feature_warp((ka, da), (kb, db), model)


def test_feature_matches_pass_the_ratio_test_strictly_below_0_75():
    """Each query descriptor has its match at distance 3 and a decoy at distance ``d``."""
    (ka, da), (kb, db) = _matches("affine", n=12)
    decoy_pts = [kp.pt for kp in kb]
    for d, n_good in ((4.1, 12), (4.0, 0), (3.9, 0)):  # 3 / 4 = 0.75 exactly is rejected
        near = db.copy()
        near[:, 0] += 3.0
        decoy = db.copy()
        decoy[:, 1] += d
        b = (kb + _keypoints(np.array(decoy_pts)[::-1]), np.vstack([near, decoy]))
        if n_good:
            w = align._feature_warp((ka, da), b, "affine")
            assert _map_error(w, _TRUE["affine"]) < 1e-3
        else:
            with pytest.raises(align._EstimationError, match=r"too few feature matches \(0\)"):
                align._feature_warp((ka, da), b, "affine")
    # 8 unambiguous matches are enough, 7 are not
    for n_good, ok in ((8, True), (7, False)):
        near = db.copy()
        near[:, 0] += 3.0
        decoy = db.copy()
        decoy[:, 1] += np.where(np.arange(12) < n_good, 10.0, 3.5)  # 3 / 3.5 fails
        b = (kb + _keypoints(np.array(decoy_pts)[::-1]), np.vstack([near, decoy]))
        if ok:
            assert _map_error(align._feature_warp((ka, da), b, "affine"), _TRUE["affine"]) < 1e-3
        else:
            with pytest.raises(align._EstimationError, match=r"too few feature matches \(7\)"):
                align._feature_warp((ka, da), b, "affine")


def test_features_stretch_the_0_5_to_99_5_percentiles_to_0_255(monkeypatch):
    seen = {}

    class Sift:
        def detectAndCompute(self, img, mask):
            seen["u8"] = img.copy()
            return ["kp"], np.zeros((1, 128), np.float32)

    def sift_create(**kw):
        seen["kw"] = kw
        return Sift()

    monkeypatch.setattr(cv2, "SIFT_create", sift_create)
    # 1000 levels 0 .. 999 / 2000: the 0.5th percentile is 4.995 / 2000, the 99.5th
    # 994.005 / 2000 (linear interpolation between the order statistics)
    ramp = (np.arange(1000, dtype=np.float32) / 2000).reshape(20, 50)
    rng = np.random.default_rng(11)
    img = rng.permutation(ramp.ravel()).reshape(20, 50)
    kp, desc = align._features(img)
    assert kp == ["kp"] and desc.shape == (1, 128)
    assert seen["kw"]["nfeatures"] > 0
    u8 = seen["u8"]
    assert u8.dtype == np.uint8 and u8.shape == img.shape
    lo, hi = 4.995, 994.005
    expect = np.clip((img.astype(float) * 2000 - lo) * 255 / (hi - lo), 0, 255)
    assert np.abs(u8 - expect).max() <= 0.5 + 1e-3
    assert (u8 == 0).sum() == 7 and (u8 == 255).sum() == 7  # 0..6 and 993..999
    # pixels darker than the 0.5th percentile are black, not mirrored to grey (a bug:
    # convertScaleAbs takes |x|, so a dark speck at 0 with the scene from 0.2 came out
    # as grey 85, brighter than the scene's darkest parts)
    scene = (0.2 + 0.6 * rng.random((40, 50))).astype(np.float32)
    scene[7, 9] = 0.0
    align._features(scene)
    assert seen["u8"][7, 9] == 0
    # a constant image does not divide by zero (estimate_alignment never passes one)
    align._features(np.full((20, 50), 0.3, np.float32))
    assert seen["u8"].shape == (20, 50)


# --- ECC --------------------------------------------------------------------------------------


def _warped_pair(shape, a):
    """A texture and its image under ``a`` (template pixel x shows at image pixel a x)."""
    t = texture(shape, seed=12, sigma=3.0)
    img = cv2.warpPerspective(
        t, a, (shape[1], shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    return t, img


@pytest.mark.parametrize(
    ("model", "truth"),
    [
        ("affine", np.array([[1.01, 0.005, 6.0], [-0.004, 0.995, -4.0], [0, 0, 1.0]])),
        ("homography", np.array([[1.0, 0.0, 5.0], [0.0, 1.0, 3.0], [2e-5, -1e-5, 1.0]])),
        (
            "similarity",
            np.array([[1.008, -0.006, 4.0], [0.006, 1.008, -5.0], [0, 0, 1.0]]),
        ),
    ],
)
def test_ecc_recovers_a_known_warp_coarse_to_fine_with_its_correlation(model, truth):
    shape = (400, 520)  # levels (100, 130), (200, 260), (400, 520)
    t, img = _warped_pair(shape, truth)
    pt, pi = align._pyramid(t), align._pyramid(img)
    assert len(pt) == 3
    w, cc = align._ecc(pt, pi, np.eye(3), model)
    inner = np.array([[60.0, 60.0], [460.0, 60.0], [60.0, 340.0], [460.0, 340.0]])
    assert np.abs(apply_h(w, inner) - apply_h(truth, inner)).max() < 0.05
    assert w[2, 2] == 1.0
    if model != "homography":
        np.testing.assert_array_equal(w[2], [0.0, 0.0, 1.0])
    # cc is the correlation at the finest level of the template with the image warped back
    back = cv2.warpPerspective(
        img, w, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    mask = np.zeros(shape, bool)
    mask[20:-20, 20:-20] = True
    assert cc == pytest.approx(ncc(t, back, mask), abs=0.01)  # ECC: Gaussian-filtered, whole
    assert cc > 0.99


def test_ecc_refines_from_a_given_start_at_a_given_level():
    truth = np.array([[1.01, 0.0, 9.0], [0.0, 1.01, -7.0], [0, 0, 1.0]])
    shape = (400, 520)
    t, img = _warped_pair(shape, truth)
    pt, pi = align._pyramid(t), align._pyramid(img)
    start = truth.copy()
    start[:2, 2] += [1.5, -1.0]  # 1.8 px off at the finest level
    inner = np.array([[60.0, 60.0], [460.0, 340.0]])
    for level in (0, 1, 2):
        w, cc = align._ecc(pt, pi, start, "affine", start_level=level)
        assert np.abs(apply_h(w, inner) - apply_h(truth, inner)).max() < 0.05, level
        assert cc > 0.99
    # a start 24 px off is reached from the coarsest level, not from the finest alone
    far = truth.copy()
    far[:2, 2] += [24.0, -20.0]
    w, _ = align._ecc(pt, pi, far, "affine", start_level=0)
    assert np.abs(apply_h(w, inner) - apply_h(truth, inner)).max() < 0.05


def test_ecc_carries_the_warp_from_each_level_to_the_next():
    """A 25 px shift is 6 px at the coarsest level: found there and doubled twice, not
    reached at the finer levels from a start left in coarse pixels."""
    truth = T(20.0, -15.0)
    t = texture((400, 520), seed=12, sigma=2.0)
    img = cv2.warpPerspective(
        t, truth, (520, 400), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    w, cc = align._ecc(align._pyramid(t), align._pyramid(img), np.eye(3), "affine")
    inner = np.array([[60.0, 60.0], [460.0, 340.0]])
    assert np.abs(apply_h(w, inner) - apply_h(truth, inner)).max() < 0.05
    assert cc > 0.99


def test_ecc_failure_is_an_estimation_error_naming_the_level():
    flat = [np.full((100, 130), 0.5, np.float32), np.full((200, 260), 0.5, np.float32)]
    with pytest.raises(align._EstimationError, match="ECC failed at pyramid level 0"):
        align._ecc(flat, flat, np.eye(3), "affine")
    tex = align._pyramid(texture((200, 260), seed=3))
    with pytest.raises(align._EstimationError, match="ECC failed at pyramid level 1"):
        align._ecc([tex[0], flat[1]], [tex[0], flat[1]], np.eye(3), "affine")


# --- estimate_alignment's choices, with the estimators stubbed -------------------------------


def T(dx, dy):
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def S(s, c=(0.0, 0.0)):
    return np.array([[s, 0.0, c[0] * (1 - s)], [0.0, s, c[1] * (1 - s)], [0.0, 0.0, 1.0]])


class Stubs:
    """Stand-ins for ``_ecc``, ``_features``, ``_feature_warp`` and ``_correlation``.

    Frame k is a texture plus 10 k, so a stub knows which frames it was given. ``table``
    maps a pair (i, j) to: ``ecc`` (w, cc) or an exception, ``feat`` a warp or an
    exception, ``fcc`` the features' correlation, ``refine`` (w, cc) or an exception.
    """

    def __init__(self, monkeypatch, table):
        self.table = table
        self.calls = []
        self.finest = (400, 480)
        monkeypatch.setattr(align, "_ecc", self.ecc)
        monkeypatch.setattr(align, "_features", lambda img: self.frame(img))
        monkeypatch.setattr(align, "_feature_warp", self.feature_warp)
        monkeypatch.setattr(align, "_correlation", self.correlation)
        # the pair matching under test; "auto"'s turn check is tested in test_align.py
        monkeypatch.setattr(align, "_turn_found", lambda *args: "")

    @staticmethod
    def frame(img) -> int:
        return round(float(np.mean(img)) / 10)

    @staticmethod
    def _give(x):
        if isinstance(x, Exception):
            raise x
        return x

    def ecc(self, ti, tj, init, model, start_level=0):
        pair = (self.frame(ti[-1]), self.frame(tj[-1]))
        if start_level == 0:
            self.calls.append(("ecc", pair))
            np.testing.assert_array_equal(init, np.eye(3))
            return self._give(self.table[pair]["ecc"])
        assert start_level == len(ti) - 1  # refine at the finest level only
        self.calls.append(("refine", pair))
        np.testing.assert_allclose(init, self.table[pair]["feat"])  # from the features' warp
        return self._give(self.table[pair]["refine"])

    def feature_warp(self, fa, fb, model):
        self.calls.append(("features", (fa, fb)))
        return self._give(self.table[(fa, fb)]["feat"])

    def correlation(self, template, image, w):
        assert template.shape == image.shape == self.finest  # the finest level
        pair = (self.frame(template), self.frame(image))
        return self.table[pair]["fcc"]


def _frames(n, shape=(400, 480)):  # pyramids of 3 levels
    base = texture(shape, seed=20)
    return [base + 10.0 * k for k in range(n)]


def _fails(msg):
    return align._EstimationError(msg)


def test_auto_accepts_a_confident_ecc_and_tries_no_features(monkeypatch):
    stubs = Stubs(monkeypatch, {(0, 1): {"ecc": (T(2.0, 1.0), 0.9)}})
    al = estimate_alignment(_frames(2), workers=0)
    assert stubs.calls == [("ecc", (0, 1))]
    a = al[0]
    assert (a.method, a.ok, a.message, a.correlation) == ("ecc", True, "", 0.9)
    np.testing.assert_allclose(a.homography, T(2.0, 1.0), atol=1e-12)
    assert a.scale == 1.0
    r = al[1]  # the default reference: len // 2
    assert (r.method, r.ok, r.scale, r.correlation) == ("reference", True, 1.0, 1.0)
    np.testing.assert_array_equal(r.homography, np.eye(3))


@pytest.mark.parametrize("ecc_cc", [0.5, 0.89])
def test_auto_checks_a_doubtful_ecc_against_features_and_keeps_it_if_they_fail(
    monkeypatch, ecc_cc
):
    """Below 0.9 ECC may sit in a false optimum (a frame moved by hand: 0.75, 40 px off):
    features are tried too; where they fail, ECC's estimate at min_correlation stands."""
    table = {(0, 1): {"ecc": (T(2.0, 1.0), ecc_cc), "feat": _fails("too few matches")}}
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2), workers=0)
    assert stubs.calls == [("ecc", (0, 1)), ("features", (0, 1))]
    a = al[0]
    assert (a.method, a.ok, a.correlation) == ("ecc", True, ecc_cc)
    np.testing.assert_allclose(a.homography, T(2.0, 1.0), atol=1e-12)


def test_auto_prefers_features_that_correlate_better_than_a_doubtful_ecc(monkeypatch):
    table = {
        (0, 1): {
            "ecc": (T(2.0, 1.0), 0.75),
            "feat": T(40.0, 0.0),
            "fcc": 0.8,
            "refine": (T(40.2, 0.0), 0.99),
        }
    }
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2), workers=0)
    assert stubs.calls == [("ecc", (0, 1)), ("features", (0, 1)), ("refine", (0, 1))]
    assert (al[0].method, al[0].correlation) == ("features+ecc", 0.99)
    np.testing.assert_allclose(al[0].homography, T(40.2, 0.0), atol=1e-12)


@pytest.mark.parametrize(
    ("fcc", "refine_cc", "winner"),
    [(0.7, 0.8, "features+ecc"), (0.85, 0.8, "features"), (0.5, 0.3, "features")],
)
def test_auto_falls_back_to_features_and_keeps_the_best_correlation(
    monkeypatch, fcc, refine_cc, winner
):
    table = {
        (0, 1): {
            "ecc": (T(2.0, 1.0), 0.49),
            "feat": T(3.0, 0.0),
            "fcc": fcc,
            "refine": (T(3.1, 0.0), refine_cc),
        }
    }
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2))
    assert stubs.calls == [("ecc", (0, 1)), ("features", (0, 1)), ("refine", (0, 1))]
    a = al[0]
    assert a.ok and a.method == winner
    want = {"features": (T(3.0, 0.0), fcc), "features+ecc": (T(3.1, 0.0), refine_cc)}[winner]
    np.testing.assert_allclose(a.homography, want[0], atol=1e-12)
    assert a.correlation == want[1]


def test_when_nothing_correlates_enough_the_reasons_are_listed_best_first(monkeypatch, caplog):
    table = {
        (0, 1): {
            "ecc": (T(2.0, 1.0), 0.49),
            "feat": T(3.0, 0.0),
            "fcc": 0.3,
            "refine": (T(3.1, 0.0), 0.45),
        }
    }
    Stubs(monkeypatch, table)
    with caplog.at_level(logging.WARNING, logger="pipeline.core.align"):
        al = estimate_alignment(_frames(2))
    a = al[0]
    assert (a.ok, a.method, a.correlation, a.scale) == (False, "fallback", None, 1.0)
    assert a.message == (
        "ecc: correlation 0.490 < min_correlation 0.5; "
        "features+ecc: correlation 0.450 < min_correlation 0.5; "
        "features: correlation 0.300 < min_correlation 0.5"
    )
    np.testing.assert_array_equal(a.homography, np.eye(3))  # the reference's
    (rec,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert rec.getMessage() == (
        f"alignment of frame 0 to frame 1 failed ({a.message}); using frame 1's transform"
    )


def test_an_implausible_ecc_estimate_sends_auto_to_features(monkeypatch):
    table = {
        (0, 1): {"ecc": (S(3.0), 0.99), "feat": T(1.0, 0.0), "fcc": 0.6, "refine": (S(0.3), 0.9)}
    }
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2), min_correlation=0.6)
    assert [c[0] for c in stubs.calls] == ["ecc", "features", "refine"]
    assert al[0].ok and al[0].method == "features" and al[0].correlation == 0.6
    # and with the features' own correlation just below min_correlation: all three fail
    table[(0, 1)]["fcc"] = 0.59
    al = estimate_alignment(_frames(2), min_correlation=0.6)
    assert al[0].message == (
        "ecc: implausible scale 3.000 (outside 0.5..2.0); "
        "features+ecc: implausible scale 0.300 (outside 0.5..2.0); "
        "features: correlation 0.590 < min_correlation 0.6"
    )


def test_ecc_only_never_tries_features_and_features_only_skips_the_first_ecc(monkeypatch):
    table = {
        (0, 1): {
            "ecc": (T(2.0, 1.0), 0.3),
            "feat": T(3.0, 0.0),
            "fcc": 0.7,
            "refine": (T(3.1, 0.0), 0.65),
        }
    }
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2), method="ecc")
    assert stubs.calls == [("ecc", (0, 1))]
    assert not al[0].ok and al[0].message == "ecc: correlation 0.300 < min_correlation 0.5"
    stubs.calls.clear()
    table[(0, 1)]["ecc"] = (T(2.0, 1.0), 0.99)  # would win, but is never computed
    al = estimate_alignment(_frames(2), method="features")
    assert stubs.calls == [("features", (0, 1)), ("refine", (0, 1))]
    assert al[0].ok and al[0].method == "features" and al[0].correlation == 0.7


def test_estimator_errors_become_the_message(monkeypatch):
    table = {(0, 1): {"ecc": _fails("ecc broke"), "feat": _fails("too few features")}}
    Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(2))
    assert al[0].message == "ecc broke; too few features"
    table[(0, 1)] = {
        "ecc": (T(1.0, 0.0), 0.2),
        "feat": T(1.0, 0.0),
        "fcc": 0.9,
        "refine": _fails("refine broke"),
    }
    al = estimate_alignment(_frames(2))  # the features' warp was a candidate already
    assert al[0].ok and al[0].method == "features" and al[0].message == ""


def test_a_textureless_frame_or_reference_is_named(monkeypatch):
    Stubs(monkeypatch, {(2, 1): {"ecc": (np.eye(3), 0.9)}})
    frames = _frames(3)
    frames[0] = np.full(frames[0].shape, 5.0, np.float32)
    al = estimate_alignment(frames, reference=1)
    assert [a.message for a in al] == ["frame 0 has no texture to match", "", ""]
    frames = _frames(3)
    frames[1] = np.full(frames[1].shape, 5.0, np.float32)
    al = estimate_alignment(frames, reference=1)
    assert [a.message for a in al] == [
        "frame 1 has no texture to match",
        "",
        "frame 1 has no texture to match",
    ]


def test_chained_transforms_compose_towards_the_reference(monkeypatch):
    w = {
        (1, 2): S(1.01, (100.0, 80.0)) @ T(0.5, -0.3),
        (0, 1): T(1.0, 2.0) @ S(0.99),
        (3, 2): S(0.98, (120.0, 90.0)),
        (4, 3): T(-2.0, 0.5) @ S(1.02, (10.0, 10.0)),
    }
    stubs = Stubs(monkeypatch, {p: {"ecc": (h, 0.9)} for p, h in w.items()})
    al = estimate_alignment(_frames(5), workers=2)
    assert sorted(p for _, p in stubs.calls) == sorted(w)  # each pair once
    pts = np.array([[0.0, 0.0], [479.0, 399.0], [37.0, 150.0]])
    expect = {
        0: apply_h(w[(1, 2)], apply_h(w[(0, 1)], pts)),
        1: apply_h(w[(1, 2)], pts),
        2: pts,
        3: apply_h(w[(3, 2)], pts),
        4: apply_h(w[(3, 2)], apply_h(w[(4, 3)], pts)),
    }
    for i, a in enumerate(al):
        assert a.ok
        np.testing.assert_allclose(map_points(a.homography, pts), expect[i], atol=1e-9)
        assert a.scale == pytest.approx(1.0 / math.sqrt(abs(np.linalg.det(a.homography[:2, :2]))))
    assert al[0].scale == pytest.approx(1 / (1.01 * 0.99))
    # unchained: every frame matched with the reference
    stubs.table = {(i, 2): {"ecc": (S(1 + 0.01 * i), 0.9)} for i in (0, 1, 3, 4)}
    stubs.calls.clear()
    al = estimate_alignment(_frames(5), chain=False)
    assert sorted(p for _, p in stubs.calls) == [(0, 2), (1, 2), (3, 2), (4, 2)]
    for i in (0, 1, 3, 4):
        np.testing.assert_allclose(al[i].homography, S(1 + 0.01 * i), atol=1e-12)


def test_a_failed_frame_is_no_anchor_and_the_fallback_is_used(monkeypatch, caplog):
    table = {
        (1, 2): {"ecc": (S(1.01), 0.9)},
        (0, 1): {"ecc": (S(1.02), 0.9)},
        (3, 2): {"ecc": _fails("no"), "feat": _fails("none")},
        (4, 3): {"ecc": (S(5.0), 0.9)},  # matched ahead, never used
        (4, 2): {"ecc": (S(0.97), 0.9)},
    }
    stubs = Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(5))
    assert [a.ok for a in al] == [True, True, True, False, True]
    np.testing.assert_array_equal(al[3].homography, np.eye(3))  # frame 2's (the anchor's)
    np.testing.assert_allclose(al[4].homography, S(0.97), atol=1e-12)
    assert ("ecc", (4, 2)) in stubs.calls
    fb = analytic_alignment([12.0, 12.1, 12.2, 12.3, 12.4], (400, 480))
    with caplog.at_level(logging.WARNING, logger="pipeline.core.align"):
        al = estimate_alignment(_frames(5), fallback=fb)
    np.testing.assert_allclose(al[3].homography, fb[3].homography, rtol=1e-15)
    assert al[3].scale == pytest.approx(12.3 / 12.2, rel=1e-12)
    assert not al[3].ok and al[3].message == "no; none"
    assert any(
        r.getMessage().endswith("using the given fallback transform") for r in caplog.records
    )


def test_a_chain_whose_product_leaves_the_plausible_range_fails_there(monkeypatch):
    table = {
        (1, 0): {"ecc": (S(1.3), 0.9)},
        (2, 1): {"ecc": (S(1.3), 0.9)},
        (3, 2): {"ecc": (S(1.3), 0.9)},
    }
    Stubs(monkeypatch, table)
    al = estimate_alignment(_frames(4), reference=0)
    assert [a.ok for a in al] == [True, True, True, False]
    assert al[3].message == "composed transform: implausible scale 2.197 (outside 0.5..2.0)"
    np.testing.assert_allclose(al[3].homography, S(1.69), rtol=1e-12)  # frame 2's
    assert al[3].scale == pytest.approx(1 / 1.69)


def test_a_reduced_estimate_is_conjugated_to_full_resolution(monkeypatch):
    """Frames 400 x 480 matched at 200 x 240: a shift of (2, 1) reduced px is (4, 2) px."""
    table = {(0, 1): {"ecc": (T(2.0, 1.0), 0.9)}, (2, 1): {"ecc": (S(1.02, (119.5, 99.5)), 0.9)}}
    Stubs(monkeypatch, table).finest = (200, 240)
    al = estimate_alignment(_frames(3, (400, 480)), max_side_px=240)
    np.testing.assert_allclose(al[0].homography, T(4.0, 2.0), atol=1e-12)
    # a scaling about the reduced image's centre is one about the full image's centre
    np.testing.assert_allclose(al[2].homography, S(1.02, (239.5, 199.5)), atol=1e-12)


def test_a_frame_with_texture_only_at_the_finest_scale_is_matched(monkeypatch):
    """A 1 px checkerboard averages to a constant one level down: only the finest level
    tells whether a frame has texture."""
    Stubs(monkeypatch, {(0, 1): {"ecc": (T(1.0, 0.0), 0.9)}})
    frames = _frames(2)
    yy, xx = np.mgrid[0:400, 0:480]
    frames[0] = (0.5 + 0.25 * ((xx + yy) % 2)).astype(np.float32)  # mean 0.625: frame 0
    assert align._is_textureless(align._pyramid(frames[0])[1])
    al = estimate_alignment(frames)
    assert al[0].ok and al[0].method == "ecc"


def test_a_reference_outside_the_frames_is_refused():
    a = texture((200, 200), seed=1)
    for bad in (2, 3, 7, -1, 1.0, "0"):
        with pytest.raises(InputError, match=r"reference must be a frame index in 0\.\.1"):
            estimate_alignment([a, a], reference=bad)
        with pytest.raises(InputError, match=r"reference must be a frame index in 0\.\.1"):
            analytic_alignment([12.0, 12.1], (10, 10), reference=bad)
    assert analytic_alignment([12.0, 12.1], (10, 10), reference=np.int32(1))[1].method == (
        "reference"
    )


# --- analytic alignment ---------------------------------------------------------------------


def test_analytic_alignment_of_a_rectangular_frame_scales_about_its_centre():
    p = [12.0, 12.5, 13.0]
    shape = (300, 500, 3)
    al = analytic_alignment(p, shape)  # reference: the middle frame
    centre = np.array([[249.5, 149.5]])
    for p_i, a in zip(p, al):
        s = 12.5 / p_i  # frame i -> reference: a scaling by p_ref / p_i
        pts = np.array([[0.0, 0.0], [499.0, 299.0], [10.0, 280.0]])
        np.testing.assert_allclose(
            map_points(a.homography, pts), centre + s * (pts - centre), rtol=1e-13
        )
        assert a.scale == pytest.approx(p_i / 12.5, rel=1e-13)
        assert a.ok and a.message == "" and a.correlation is None
    assert [a.method for a in al] == ["analytic", "reference", "analytic"]
    np.testing.assert_allclose(al[1].homography, np.eye(3), atol=1e-15)
    (one,) = analytic_alignment(np.array([[7.0]]), (1, 1))
    assert one.method == "reference" and one.scale == 1.0


@pytest.mark.parametrize("shape", [(0, 5), (5, 0), (5,), (), (-1, 4)])
def test_analytic_alignment_needs_rows_and_cols(shape):
    with pytest.raises(InputError, match=r"shape must start with \(rows, cols\) >= 1"):
        analytic_alignment([12.0, 12.5], shape)


# --- warp -----------------------------------------------------------------------------------


def _bilinear(img, x, y):
    """img sampled at (x, y) by hand, edge pixels replicated."""
    rows, cols = img.shape[:2]
    x = np.clip(x, 0, cols - 1)
    y = np.clip(y, 0, rows - 1)
    x0 = np.minimum(np.floor(x).astype(int), cols - 2) if cols > 1 else np.zeros_like(x, int)
    y0 = np.minimum(np.floor(y).astype(int), rows - 2) if rows > 1 else np.zeros_like(y, int)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    fx, fy = fx[..., None], fy[..., None]
    im = img.astype(float).reshape(rows, cols, -1)
    return (1 - fy) * ((1 - fx) * im[y0, x0] + fx * im[y0, x1]) + fy * (
        (1 - fx) * im[y1, x0] + fx * im[y1, x1]
    )


@pytest.mark.parametrize("channels", [None, 1, 2, 3, 4, 5, 6, 8, 9])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_warp_resamples_every_channel_bilinearly(channels, dtype):
    rng = np.random.default_rng(13)
    shape = (30, 40) if channels is None else (30, 40, channels)
    x = (rng.random(shape) * 1000).astype(dtype)
    h = np.array([[1.04, 0.02, -1.3], [-0.01, 0.97, 2.2], [2e-4, -1e-4, 1.0]])
    out = warp(x, h, (26, 35, 99))  # only the first two entries of shape count
    want_shape = (26, 35) if channels is None else (26, 35, channels)
    assert out.shape == want_shape
    assert out.dtype == (np.float32 if dtype == np.float32 else np.float64)
    yy, xx = np.mgrid[0:26, 0:35].astype(float)
    src = apply_h(np.linalg.inv(h), np.c_[xx.ravel(), yy.ravel()])
    ref = _bilinear(x, src[:, 0], src[:, 1]).reshape(26, 35, -1)
    # 1/32 px quantised positions would be up to ~10 off here
    np.testing.assert_allclose(out.reshape(26, 35, -1), ref, rtol=1e-5, atol=0.01)


def test_warp_coverage_is_fractional_on_the_edge():
    x = texture((20, 30), seed=14)
    out, cov = warp(x, T(0.5, -0.25), (20, 30), return_coverage=True)
    assert cov.dtype == np.float32 and cov.shape == (20, 30)
    # out(x) = frame(x - 0.5, y + 0.25): column 0 is half outside, the last row a quarter
    np.testing.assert_allclose(cov[:-1, 0], 0.5, atol=1e-6)
    np.testing.assert_allclose(cov[-1, 1:], 0.75, atol=1e-6)
    assert cov[-1, 0] == pytest.approx(0.375, abs=1e-6)
    np.testing.assert_array_equal(cov[:-1, 1:], 1.0)
    # the values there are extrapolated by replicating the edge, not faded to black
    np.testing.assert_allclose(out[5, 0], x[5, 0] * 0.75 + x[6, 0] * 0.25, rtol=1e-5)
    one = warp(np.full((1, 1), 2.0, np.float32), np.eye(3), (1, 1), return_coverage=True)
    assert one[0].shape == (1, 1) and one[0][0, 0] == 2.0 and one[1][0, 0] == 1.0


@pytest.mark.parametrize("shape", [(0, 5), (5, 0), (5,), (-3, 5)])
def test_warp_needs_an_output_of_at_least_one_pixel(shape):
    with pytest.raises(InputError, match=r"shape must start with \(rows, cols\) >= 1"):
        warp(np.ones((4, 4), np.float32), np.eye(3), shape)


def test_implausible_names_the_worst_perspective_and_the_determinant():
    shape = (480, 640)
    h = np.eye(3)
    h[2, 0] = 1e-4  # w = 1 + 1e-4 x: 1.0639 at the far corners
    assert align._implausible(h, shape) == "strong perspective terms (|w - 1| up to 0.064)"
    h[2, 1] = -2e-4  # w = 1 - 2e-4 * 479 at (0, 479): 0.9042
    assert align._implausible(h, shape) == "strong perspective terms (|w - 1| up to 0.096)"
    assert align._implausible(np.diag([-2.0, 3.0, 1.0]), shape) == (
        "degenerate or mirroring homography (det of linear part -6)"
    )
    assert align._implausible(2.0 * np.diag([3.0, 3.0, 1.0]), shape) == (
        "implausible scale 3.000 (outside 0.5..2.0)"
    )


def test_frames_of_another_size_are_refused_larger_or_smaller_grey_or_colour():
    a = texture((100, 200), seed=2)
    for other in ((100, 199), (99, 200), (101, 200), (100, 201)):
        b = texture(other, seed=3)
        with pytest.raises(InputError, match=rf"frames\[1\] has size \({other[0]}, {other[1]}\)"):
            estimate_alignment([a, b])
    colour = np.dstack([a] * 3)
    with pytest.raises(
        InputError, match=r"frames\[1\] has size \(100, 199\) but frames\[0\] has \(100, 200\);"
    ):
        estimate_alignment([colour, np.dstack([texture((100, 199), seed=3)] * 3)])


def test_perspective_is_limited_at_the_frame_corners_not_a_pixel_beyond():
    """|w - 1| is linear in (x, y): its largest value over the frame is at a corner. With
    the other perspective term of the opposite sign, a point one pixel outside the frame
    would exceed the limit where no pixel of the frame does."""
    shape = (480, 640)
    for axis, far in ((0, 639), (1, 479)):
        h = np.eye(3)
        h[2, 1 - axis] = -6e-5
        h[2, axis] = 0.04997 / far
        assert align._implausible(h, shape) == "", axis
        h[2, axis] = 0.05003 / far
        assert "perspective" in align._implausible(h, shape), axis


def test_a_fallback_for_a_stack_of_more_than_256_frames_is_accepted():
    """Lengths compared by value: ints above 256 are distinct objects in CPython."""
    n = 300
    frames = [np.full((8, 8), 1.0 + k, np.float32) for k in range(n)]  # textureless: fast
    fb = analytic_alignment(np.linspace(12.0, 13.0, n), (8, 8))
    al = estimate_alignment(frames, fallback=fb)
    assert len(al) == n and al[0].method == "fallback"
    np.testing.assert_array_equal(al[0].homography, fb[0].homography)
