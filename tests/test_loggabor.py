import cv2
import numpy as np
import pytest
import scipy.fft as sfft

from bb_align.engine.config import MimConfig
from bb_align.engine.loggabor import (
    _circular_span,
    angular_filters,
    fft_shape,
    filter_bank,
    frequency_grid,
    maximum_index_map,
    orientation_amplitudes,
)


def _direct(i, j, shape, s, o, cfg):
    """The bank's value at FFT bin (i, j), evaluated from the formulas in ALGORITHM.md one number at a time."""
    v = sfft.fftfreq(shape[0])[i]
    u = sfft.fftfreq(shape[1])[j]
    r = np.sqrt(u * u + v * v)
    if r == 0:
        return 0.0
    theta = np.arctan2(-v, u)
    lowpass = 1.0 / (1.0 + (r / 0.45) ** 30)
    f0 = 1.0 / (3.0 * 1.6**s)
    radial = np.exp(-(np.log(r / f0) ** 2) / (2 * np.log(0.75) ** 2)) * lowpass
    phi = o * np.pi / 12
    d = abs(np.arctan2(np.sin(theta - phi), np.cos(theta - phi)))
    d = min(d * 12, np.pi)
    return radial * (np.cos(d) + 1) / 2


def test_filter_bank_matches_direct_formula():
    cfg = MimConfig()
    shape = (48, 60)
    bank = filter_bank(shape, cfg)
    assert bank.shape == (12, 4, 48, 60)
    rng = np.random.default_rng(0)
    for _ in range(300):
        i, j, s, o = rng.integers(48), rng.integers(60), rng.integers(4), rng.integers(12)
        assert bank[o, s, i, j] == pytest.approx(_direct(i, j, shape, s, o, cfg), abs=1e-6)
    assert filter_bank(shape, cfg) is bank, "the bank is built once per shape"


def test_angular_windows_partition_the_half_plane():
    cfg = MimConfig()
    _, theta = frequency_grid((64, 64))
    total = angular_filters(theta, cfg).sum(0)
    upper = (theta >= 0) & (theta <= np.pi * 11 / 12)
    np.testing.assert_allclose(total[upper], 1.0, atol=1e-9)
    assert np.all(total[(theta < -np.pi / 12) & (theta > -np.pi * 11 / 12)] == 0), "one-sided in angle"


def _segments_image(size=320, seed=0):
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.uint8)
    c = size / 2
    for _ in range(40):
        a = rng.uniform(0, np.pi)
        x0, y0 = rng.uniform(c - 90, c + 90, 2)
        L = rng.uniform(10, 40)
        p0 = (int(x0), int(y0))
        p1 = (int(x0 + L * np.cos(a)), int(y0 + L * np.sin(a)))
        cv2.line(img, p0, p1, int(rng.integers(80, 255)), 2)
    return img


def test_mim_quarter_turn_shifts_values_by_six_exactly():
    img = _segments_image()
    mim, _ = maximum_index_map(img)
    mim90, _ = maximum_index_map(np.rot90(img).copy())  # counter-clockwise on screen
    back = np.rot90(mim90, -1)
    lit = (mim > 0) & (back > 0)
    assert lit.sum() > 1000
    shift = (back[lit].astype(int) - mim[lit]) % 12
    assert np.mean(shift == 6) > 0.99


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_mim_rotation_by_15k_degrees_shifts_values_by_k(k):
    img = _segments_image(seed=k)
    size = img.shape[0]
    M = cv2.getRotationMatrix2D((size / 2 - 0.5, size / 2 - 0.5), 15.0 * k, 1.0)  # CCW on screen
    rot = cv2.warpAffine(img, M, (size, size), flags=cv2.INTER_LINEAR)
    mim, amp = maximum_index_map(img)
    mim_r, _ = maximum_index_map(rot)
    # Compare at strong, well-inside pixels of the original, mapped through the rotation.
    rc = np.argwhere((mim > 0) & (amp > np.percentile(amp[mim > 0], 50)))
    xy = np.column_stack([rc[:, 1], rc[:, 0], np.ones(len(rc))]) @ M.T
    r2, c2 = np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)
    ok = (r2 >= 0) & (r2 < size) & (c2 >= 0) & (c2 < size)
    v0, v1 = mim[rc[ok, 0], rc[ok, 1]].astype(int), mim_r[r2[ok], c2[ok]].astype(int)
    lit = v1 > 0
    shift = (v1[lit] - v0[lit]) % 12
    assert np.mean(shift == k) > 0.6
    assert np.mean(np.isin(shift, [(k - 1) % 12, k, (k + 1) % 12])) > 0.9


def test_mim_of_empty_image_is_zero():
    mim, amp = maximum_index_map(np.zeros((50, 70), np.uint8))
    assert mim.shape == (50, 70) and mim.max() == 0 and np.all(amp == 0)


def test_threaded_mim_equals_sequential():
    img = _segments_image(seed=11)
    m1, a1 = maximum_index_map(img, MimConfig(threads=1))
    for threads in (2, 5):
        m2, a2 = maximum_index_map(img, MimConfig(threads=threads))
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(a1, a2)


def _amplitudes_by_numpy(img, cfg):
    """A_o = sum_s |IFFT2(F * G_s * S_o)| in complex128 with numpy, the dense bank, no tricks: the reference."""
    m = cfg.fft_margin_px
    shape = fft_shape(img.shape, m)
    padded = np.zeros(shape)
    padded[m : m + img.shape[0], m : m + img.shape[1]] = img
    spectrum = np.fft.fft2(padded)
    bank = filter_bank(shape, cfg).astype(np.float64)
    out = np.abs(np.fft.ifft2(spectrum[None, None] * bank, axes=(-2, -1))).sum(axis=1)
    return out[:, m : m + img.shape[0], m : m + img.shape[1]]


@pytest.mark.parametrize(
    "origin,shape,margin", [((0, 0), (200, 200), 16), ((50, 40), (90, 130), 0), ((45, 95), (7, 5), 3)]
)
def test_amplitudes_equal_dense_complex128_transforms(origin, shape, margin):
    """The boxed, shifted float32 transforms give the dense complex128 transforms' amplitudes (square and
    rectangular transforms, boxes that wrap around the spectrum's edges, boxes as large as the spectrum)."""
    img = _segments_image(size=200, seed=3)[origin[0] : origin[0] + shape[0], origin[1] : origin[1] + shape[1]]
    assert np.count_nonzero(img) >= 15
    cfg = MimConfig(fft_margin_px=margin, coarse_scales=0)  # every scale at full resolution: exact
    reference = _amplitudes_by_numpy(img, cfg)
    ours = np.stack([a.copy() for _, a in orientation_amplitudes(img.astype(np.float32), cfg)])
    np.testing.assert_allclose(ours, reference, atol=2e-5 * reference.max())


@pytest.mark.parametrize("shape,margin", [((201, 201), 16), ((151, 199), 5)])
def test_decimated_scales_are_exact_on_their_lattice(shape, margin):
    """Scales computed on the half-resolution grid: on the lattice they were sampled at (every 2nd FFT-grid pixel;
    odd image sizes put it on whole pixels) the amplitudes equal the dense complex128 transforms'; between lattice
    points they are interpolated, so close but not equal."""
    img = _segments_image(size=210, seed=5)[: shape[0], : shape[1]]
    cfg = MimConfig(fft_margin_px=margin, coarse_scales=4, coarse_stride=2)
    from bb_align.engine.loggabor import lattice_shift

    assert lattice_shift(img.shape, cfg) == (0.0, 0.0)
    reference = _amplitudes_by_numpy(img, cfg)
    ours = np.stack([a.copy() for _, a in orientation_amplitudes(img.astype(np.float32), cfg)])
    on = (slice(None), slice(margin % 2, None, 2), slice(margin % 2, None, 2))  # (m + i) even
    np.testing.assert_allclose(ours[on], reference[on], atol=2e-5 * reference.max())
    off = (slice(None), slice(1 - margin % 2, None, 2), slice(None))
    assert not np.allclose(ours[off], reference[off], atol=2e-5 * reference.max())
    assert np.abs(ours - reference).max() < 0.2 * reference.max()


def test_decimated_mim_agrees_with_the_exact_one_on_a_real_scan(shared_data):
    """The one approximation of the default MIM (every scale decimated, amplitudes interpolated) changes the
    orientation index at a few % of the lit pixels of a real BV image: 95.1 % agree on this KITTI scan, 97 % on
    simulated ones (docs/acquisition.md, Speed). A broken lattice or phase would leave far fewer."""
    from bb_align.engine.bev import make_bev
    from bb_align.engine.config import BevConfig
    from realdata import kitti_scan

    image = make_bev(kitti_scan(shared_data, "000000")[:, :3], BevConfig(range_m=100)).image
    exact, _ = maximum_index_map(image, MimConfig(coarse_scales=0))
    fast, _ = maximum_index_map(image, MimConfig())
    lit = image > 0
    assert MimConfig().coarse_scales == 4 and lit.sum() > 5000
    assert np.mean(fast[lit] == exact[lit]) > 0.93


@pytest.mark.parametrize(
    "shape,offset,stride,resized",
    [((20, 24), (15.5, 15.5), 2, True), ((20, 24), (16.0, 15.5), 2, False), ((9, 9), (0.5, 0.5), 2, False),
     ((12, 10), (13.0, 13.0), 3, True)],
)  # fmt: skip
def test_upsampling_is_the_periodic_bilinear_interpolation(shape, offset, stride, resized, monkeypatch):
    """acc += coarse at ((offset + i) / stride, (offset + j) / stride), bilinear on the periodic coarse map, checked
    point by point; both of _add_upsampled's ways (the cropped enlargement when the pixels line up, the wrapping
    warp otherwise, here also at the border) give it."""
    from bb_align.engine.loggabor import _add_upsampled

    rng = np.random.default_rng(1)
    coarse = rng.random((20, 22)).astype(np.float32)
    acc = rng.random(shape).astype(np.float32)
    expected = acc.astype(np.float64)
    for i in range(shape[0]):
        for j in range(shape[1]):
            r, c = (offset[0] + i) / stride, (offset[1] + j) / stride
            r0, c0 = int(np.floor(r)), int(np.floor(c))
            fr, fc = r - r0, c - c0
            at = lambda a, b: float(coarse[a % coarse.shape[0], b % coarse.shape[1]])  # noqa: E731
            expected[i, j] += (1 - fr) * ((1 - fc) * at(r0, c0) + fc * at(r0, c0 + 1)) + fr * (
                (1 - fc) * at(r0 + 1, c0) + fc * at(r0 + 1, c0 + 1)
            )
    calls = []
    monkeypatch.setattr(cv2, "resize", lambda *a, **k: calls.append(1) or _resize(*a, **k))
    _add_upsampled(acc, coarse, offset, stride, np.empty((20 * stride, 22 * stride), np.float32))
    assert bool(calls) == resized
    np.testing.assert_allclose(acc, expected, atol=1e-5)


_resize = cv2.resize


def test_circular_span_hand_worked():
    mask = np.zeros(10, bool)
    mask[[0, 1, 8, 9]] = True  # wraps around: rows 8, 9, 0, 1
    assert _circular_span(mask) == (8, 4)
    mask = np.zeros(10, bool)
    mask[3:6] = True
    assert _circular_span(mask) == (3, 3)
    assert _circular_span(np.ones(7, bool)) == (0, 7)


def test_fft_size_is_the_smallest_fast_length():
    """Brute force over lengths: a multiple of 16 whose odd part is 3-, 5- and 7-smooth, the smallest >= n."""
    from bb_align.engine.loggabor import fft_size

    def fast(m: int) -> bool:
        if m % 16:
            return False
        for p in (2, 3, 5, 7):
            while m % p == 0:
                m //= p
        return m == 1

    for n in range(1, 1200):
        assert fft_size(n) == next(m for m in range(max(n, 16), 4 * n + 32) if fast(m))
    assert fft_size(532) == 560 and fft_size(432) == 432  # a 500 px image with its 16 px margins; a 400 px one
