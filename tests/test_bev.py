import numpy as np
import pytest

from bb_align.engine.bev import BevImage, decode_png, image_size_px, make_bev
from bb_align.engine.config import BevConfig


def test_pixel_metre_round_trip():
    bev = BevImage(np.zeros((400, 400), np.uint8), resolution_m=0.4, range_m=80.0)
    xy = np.random.default_rng(0).uniform(-79, 79, (100, 2))
    np.testing.assert_allclose(bev.pixel_to_metre(bev.metre_to_pixel(xy)), xy, atol=1e-9)
    # Hand-worked: the pixel centred 0.2 m ahead and 0.2 m left of the sensor is (199, 199);
    # forward is up (row decreases with x), left is left (column decreases with y).
    np.testing.assert_allclose(bev.pixel_to_metre([[199, 199]]), [[0.2, 0.2]])
    np.testing.assert_allclose(bev.pixel_to_metre([[0, 399]]), [[79.8, -79.8]])


def test_points_land_in_the_documented_pixels_with_height_values():
    cfg = BevConfig(range_m=20.0, resolution_m=0.5, ground_clearance_m=0.3, max_height_m=10.3)
    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-19, 19, (20000, 2)), np.full(20000, -1.7)])
    pole = np.array([[5.1, -3.1, -1.7 + h] for h in np.linspace(0.0, 5.0, 51)])  # 5 m above ground
    bev = make_bev(np.vstack([ground, pole]), cfg)
    assert bev.shape == (image_size_px(cfg),) * 2 == (80, 80)
    r, c = np.round(bev.metre_to_pixel([[5.1, -3.1]])[0]).astype(int)
    assert (r, c) == (29, 46)  # floor((20 - 5.1) / 0.5), floor((20 + 3.1) / 0.5)
    # value = 1 + round((5.0 - 0.3) / (10.3 - 0.3) * 254) = 120; decodes back to 5.0 m within a level
    assert bev.image[r, c] == 120
    assert bev.heights_m()[r, c] == pytest.approx(5.0, abs=0.04)
    lit = np.argwhere(bev.image > 0)
    assert len(lit) == 1, "flat ground must not light up the image"


def test_slices_mode_counts_occupied_slices():
    cfg = BevConfig(range_m=10.0, resolution_m=0.4, mode="slices", ground_clearance_m=0.3, slice_m=0.2)
    ground = np.column_stack([np.random.default_rng(0).uniform(-9, 9, (5000, 2)), np.zeros(5000)])
    column = np.array([[1.0, 1.0, z] for z in (0.35, 0.45, 0.75, 0.95)])  # slices 0, 0, 2, 3 -> 3 occupied
    bev = make_bev(np.vstack([ground, column]), cfg)
    r, c = np.round(bev.metre_to_pixel([[1.0, 1.0]])[0]).astype(int)
    assert bev.image[r, c] == 30


def test_png_round_trip_and_meta():
    img = np.random.default_rng(0).integers(0, 255, (64, 48), dtype=np.uint8)
    bev = BevImage(img, resolution_m=0.4, range_m=12.8)
    again = BevImage.from_png(bev.to_png(), **bev.meta())
    np.testing.assert_array_equal(again.image, img)
    assert again.meta() == bev.meta()


def test_bad_inputs_are_refused_clearly():
    with pytest.raises(ValueError, match="points must be"):
        make_bev(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="uint8"):
        BevImage(np.zeros((4, 4), np.float32), 0.4, 1.0)
    with pytest.raises(ValueError, match="PNG"):
        decode_png(b"not a png")
    assert make_bev(np.full((5, 3), np.nan)).image.max() == 0
