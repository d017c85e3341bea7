import numpy as np
import pytest

from bb_align.engine.config import FeatureConfig
from bb_align.engine.descriptors import bvft_descriptors, flip_180
from bb_align.engine.loggabor import maximum_index_map
from test_loggabor import _segments_image


def _desc(img, rc, cfg=None):
    mim, amp = maximum_index_map(img)
    return bvft_descriptors(mim, amp, rc, cfg)


@pytest.fixture(scope="module")
def scene():
    img = _segments_image(size=320, seed=7)
    rc = np.argwhere(img > 0)
    rc = rc[np.random.default_rng(0).choice(len(rc), 40, replace=False)]
    return img, rc


def test_dimensions_and_unit_norm(scene):
    img, rc = scene
    d216 = _desc(img, rc)
    d432 = _desc(img, rc, FeatureConfig(merge_bins=False))
    assert d216.shape == (40, 216) and d432.shape == (40, 432)
    np.testing.assert_allclose(np.linalg.norm(d216, axis=1), 1.0, rtol=1e-5)


def test_empty_patch_gives_zero_descriptor_not_nan():
    d = _desc(np.zeros((200, 200), np.uint8), np.array([[100, 100], [0, 0]]))
    assert np.all(d == 0) and not np.isnan(d).any()


def test_quarter_turn_gives_the_same_or_the_flipped_descriptor(scene):
    img, rc = scene
    size = img.shape[0]
    d0 = _desc(img, rc)
    rc90 = np.column_stack([size - 1 - rc[:, 1], rc[:, 0]])  # np.rot90: (r, c) -> (W-1-c, r)
    d1 = _desc(np.rot90(img).copy(), rc90)
    # MIM values live in [0, pi): where the turn wraps a keypoint's dominant orientation past 180 degrees its
    # window is sampled half a turn away, so it matches the 180-degree copy instead (why matching uses both).
    cos = np.maximum((d0 * d1).sum(1), (flip_180(d0) * d1).sum(1))
    assert np.median(cos) > 0.97
    assert np.mean(cos > 0.9) > 0.9


def test_half_turn_gives_the_flipped_descriptor(scene):
    img, rc = scene
    size = img.shape[0]
    d0 = _desc(img, rc)
    rc180 = size - 1 - rc
    d1 = _desc(np.rot90(img, 2).copy(), rc180)
    same = np.median((d0 * d1).sum(1))
    flipped = np.median((flip_180(d0) * d1).sum(1))
    assert flipped > 0.97, "the 180-degree copy must match the half-turned scene"
    assert flipped > same + 0.1, "and it must be needed: the plain descriptor matches worse"


def test_threaded_prepare_gives_the_same_features():
    from bb_align import AlignConfig, Aligner
    from bb_align.engine.config import MimConfig

    img = _segments_image(size=320, seed=3)
    from bb_align.engine.bev import BevImage

    bev = BevImage(img, resolution_m=0.4, range_m=64.0)
    one = Aligner(AlignConfig(mim=MimConfig(threads=1), features=FeatureConfig(threads=1))).prepare(bev)
    two = Aligner(AlignConfig(features=FeatureConfig(threads=3))).prepare(bev)
    np.testing.assert_array_equal(one.descriptors, two.descriptors)
    np.testing.assert_array_equal(one.keypoints_rc, two.keypoints_rc)
    np.testing.assert_array_equal(
        one.reference_descriptors(one_cfg := FeatureConfig(threads=1), 12), two.reference_descriptors(one_cfg, 12)
    )
