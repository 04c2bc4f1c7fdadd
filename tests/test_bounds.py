"""service/bounds.py's apparent size against closed forms, and its 422s where no request test reaches."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from service.bounds import APPARENT_FLOOR_PX, MIN_APPARENT_PX, apparent_size_px, check_apparent_size
from service.errors import UnprocessableError
from service.schemas import Camera, Options


def _bank(extents_mm, centre_obj=(0.0, 0.0, 0.0)):
    e = np.asarray(extents_mm, float)
    return SimpleNamespace(extents_mm=e, centre_obj=np.asarray(centre_obj, float),
                           diameter_mm=float(np.linalg.norm(e)))


@pytest.mark.parametrize("r, z", [(100.0, 500.0), (10.0, 20.0), (50.0, 51.0)])
def test_on_the_axis_a_sphere_appears_2_f_r_over_sqrt_z2_minus_r2(r, z):
    """The tangent cone of a sphere of radius r at depth z on the optical axis: half-angle asin(r / z),
    so 2 f tan(asin(r / z)) across. A 1 x 1 image sees only (nearly) the axis."""
    cam = Camera(fx=1000.0, fy=1000.0, cx=0.0, cy=0.0)
    expected = 2000.0 * r / math.sqrt(z * z - r * r)
    assert apparent_size_px(r, z, cam, (1, 1)) == pytest.approx(expected, rel=1e-5)


def test_a_sphere_reaching_the_camera_has_no_size_and_the_corners_see_it_larger():
    cam = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5)
    assert apparent_size_px(100.0, 100.0, cam, (640, 480)) == math.inf
    assert apparent_size_px(100.0, 50.0, cam, (640, 480)) == math.inf
    # the corner ray is 33.7 deg off the axis (tan = 400 / 600): a far sphere at the same depth lies
    # 1 / cos farther along it, and the image stretches angles there by 1 / cos^2: 1 / cos in all
    far = apparent_size_px(1.0, 10_000.0, cam, (640, 480))
    assert far == pytest.approx(2 * 600.0 * 1.0 / 10_000.0 * math.hypot(1.0, 400 / 600), rel=1e-4)


def test_a_part_too_small_to_see_is_422_naming_the_distance_and_the_fix():
    """A 3 mm part at 20 m with fx 1100: 0.2 px, under one level-A pixel (8 px); 8 px at the image's corner
    (tan = 800 / 1100 off the axis): z = 2 f r / 8 / cos = 2 x 1100 x 1.5 / 8 x 1.236 = 510 mm."""
    cam = Camera(fx=1100.0, fy=1100.0, cx=639.5, cy=479.5)
    with pytest.raises(UnprocessableError) as e:
        check_apparent_size(_bank([1.0, 2.0, 2.0]), cam, Options(distance_mm=20_000.0), (1280, 960))
    assert f"under the {MIN_APPARENT_PX:g} px the search can see" in e.value.detail
    assert "send a distance_mm of at most 510 mm" in e.value.detail
    check_apparent_size(_bank([1.0, 2.0, 2.0]), cam, Options(distance_mm=400.0), (1280, 960))


def test_the_bound_of_a_small_image_is_the_floor():
    """A 64 x 64 image allows 1024 px (the floor), not 4 x 64: a 100 mm ball at 200 mm with fx 1000
    (580 px across) passes there, at 100.5 mm (~10,000 px) it does not."""
    cam = Camera(fx=1000.0, fy=1000.0, cx=31.5, cy=31.5)
    bank = _bank([100.0, 0.0, 0.0])
    check_apparent_size(bank, cam, Options(distance_range_mm=(200.0, 900.0)), (64, 64))
    with pytest.raises(UnprocessableError) as e:
        check_apparent_size(bank, cam, Options(distance_range_mm=(50.5, 900.0)), (64, 64))
    floor = f"more than the {APPARENT_FLOOR_PX:.0f} px the search allows in this 64 x 64 image"
    assert floor in e.value.detail
    assert "options.distance_range_mm with a low end of at least" in e.value.detail


def test_distance_mm_is_the_origins_so_the_reference_point_offset_counts():
    """The sprayer's reference point is 100 mm from its origin (its base): distance_mm 150 puts the
    reference point 50 mm from the camera, inside the part's 109 mm bounding sphere."""
    cam = Camera(fx=1100.0, fy=1100.0, cx=639.5, cy=479.5)
    sprayer = _bank([60.0, 200.0, 60.0], centre_obj=(0.0, 100.0, 0.0))
    with pytest.raises(UnprocessableError) as e:
        check_apparent_size(sprayer, cam, Options(distance_mm=150.0), (1280, 960))
    assert "would reach the camera at options.distance_mm (150 mm)" in e.value.detail
    check_apparent_size(sprayer, cam, Options(distance_mm=500.0), (1280, 960))
