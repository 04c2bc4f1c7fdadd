"""decode: every accepted mesh/image format, unit conversion, and each kind of bad file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from service import decode
from service.decode import decode_image, decode_mesh
from service.errors import ServiceError, TooLargeError, UnprocessableError, UnsupportedMediaError

RNG_SEED = 7


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box((10.0, 20.0, 30.0))


def _export(mesh: trimesh.Trimesh | trimesh.Scene, file_type: str) -> bytes:
    data = mesh.export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


def _png(img: np.ndarray, ext: str = ".png") -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def _assert_sentence(err: ServiceError) -> None:
    assert err.detail.endswith(".") and "\n" not in err.detail


# --- meshes -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("file_type, ext", [("stl", "stl"), ("stl_ascii", "stl"), ("obj", "obj"),
                                            ("ply", "ply"), ("off", "off"), ("glb", "glb")])
def test_every_mesh_format_decodes_in_mm(file_type, ext):
    mesh = decode_mesh(_export(_box(), file_type), f"part.{ext.upper()}", "mm")
    np.testing.assert_allclose(mesh.extents, [10.0, 20.0, 30.0])
    assert len(mesh.faces) == 12


@pytest.mark.parametrize("units, scale", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0), ("in", 25.4)])
def test_units_are_converted_once(units, scale):
    mesh = decode_mesh(_export(_box(), "stl"), "part.stl", units)
    np.testing.assert_allclose(mesh.extents, np.array([10.0, 20.0, 30.0]) * scale)


def test_real_stl_and_ply(data_dir):
    sprayer = decode_mesh((data_dir / "models" / "sprayer.stl").read_bytes(), "sprayer.stl")
    np.testing.assert_allclose(sprayer.extents, [60.0, 200.0, 60.0], atol=1e-6)
    tless = decode_mesh((data_dir / "models" / "tless_06.ply").read_bytes(), "tless_06.ply")
    assert len(tless.faces) > 0


def test_scene_is_merged_with_its_transforms():
    sphere = trimesh.creation.icosphere(radius=1.0).apply_translation([50.0, 0.0, 0.0])
    mesh = decode_mesh(_export(trimesh.Scene([_box(), sphere]), "glb"), "two.glb")
    assert len(mesh.faces) == 12 + len(sphere.faces)
    np.testing.assert_allclose(mesh.bounds[:, 0], [-5.0, 51.0], atol=1e-6)


def test_open_mesh_is_accepted():
    box = _box()
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])
    mesh = decode_mesh(_export(open_box, "stl"), "open.stl")
    assert not mesh.is_watertight and len(mesh.faces) == 10


@pytest.mark.parametrize("filename", ["part.step", "part", "part.stl.txt"])
def test_unknown_extension_is_415(filename):
    with pytest.raises(UnsupportedMediaError) as e:
        decode_mesh(_export(_box(), "stl"), filename)
    _assert_sentence(e.value)


@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "off", "glb"])
def test_garbage_is_415_or_422(ext):
    with pytest.raises((UnsupportedMediaError, UnprocessableError)) as e:
        decode_mesh(b"this is not a mesh at all\n" * 20, f"x.{ext}")
    _assert_sentence(e.value)


def test_truncated_stl_is_rejected():
    data = _export(trimesh.creation.icosphere(), "stl")
    with pytest.raises((UnsupportedMediaError, UnprocessableError)):
        decode_mesh(data[: len(data) // 2], "half.stl")


def test_empty_file_is_422():
    with pytest.raises(UnprocessableError, match="empty"):
        decode_mesh(b"", "empty.stl")


@pytest.mark.parametrize("obj, words", [
    (b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
    (b"v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n", "zero extent"),
    (b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "zero extent"),
])
def test_unusable_geometry_is_422(obj, words):
    with pytest.raises(UnprocessableError, match=words) as e:
        decode_mesh(obj, "bad.obj")
    _assert_sentence(e.value)


def test_point_cloud_is_422():
    cloud = trimesh.PointCloud(np.random.default_rng(RNG_SEED).random((20, 3))).export(file_type="ply")
    with pytest.raises(UnprocessableError, match="faces"):
        decode_mesh(cloud, "cloud.ply")


def test_face_limit_is_422(monkeypatch):
    monkeypatch.setattr(decode, "MAX_MESH_FACES", 11)
    with pytest.raises(UnprocessableError, match="faces"):
        decode_mesh(_export(_box(), "stl"), "box.stl")


def test_unknown_unit_is_422():
    with pytest.raises(UnprocessableError, match="unit"):
        decode_mesh(_export(_box(), "stl"), "box.stl", "ft")


# --- images -----------------------------------------------------------------------------------------

_rng = np.random.default_rng(RNG_SEED)
GREY8 = _rng.integers(0, 256, (40, 60), dtype=np.uint8)
GREY16 = _rng.integers(0, 65536, (40, 60), dtype=np.uint16)
BGR8 = _rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
BGR16 = _rng.integers(0, 65536, (40, 60, 3), dtype=np.uint16)


@pytest.mark.parametrize("ext, img", [(".png", GREY8), (".png", GREY16), (".bmp", GREY8), (".tif", GREY8),
                                      (".tif", GREY16)])
def test_lossless_grey_images_round_trip(ext, img):
    out = decode_image(_png(img, ext))
    assert out.dtype == img.dtype and out.shape == img.shape
    np.testing.assert_array_equal(out, img)


@pytest.mark.parametrize("ext, img", [(".png", BGR8), (".png", BGR16), (".bmp", BGR8), (".tif", BGR16)])
def test_lossless_colour_images_stay_bgr(ext, img):
    out = decode_image(_png(img, ext))
    assert out.shape == img.shape and out.dtype == img.dtype
    np.testing.assert_array_equal(out, img)


def test_jpeg_and_alpha():
    assert decode_image(_png(BGR8, ".jpg")).shape == (40, 60, 3)
    bgra = np.dstack([BGR8, np.full((40, 60), 255, np.uint8)])
    np.testing.assert_array_equal(decode_image(_png(bgra)), BGR8)


def test_real_render(data_dir):
    img = decode_image((data_dir / "paper" / "images" / "0001.png").read_bytes())
    assert img.shape[:2] == (960, 1280) and img.dtype == np.uint8


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tif"])
def test_truncated_image_is_rejected(ext):
    data = _png(BGR8, ext)
    with pytest.raises((UnprocessableError, UnsupportedMediaError)) as e:
        decode_image(data[: len(data) // 2])
    _assert_sentence(e.value)


def test_not_an_image_is_415():
    with pytest.raises(UnsupportedMediaError):
        decode_image(b"GIF? no, just text " * 10)


def test_empty_image_is_422():
    with pytest.raises(UnprocessableError, match="empty"):
        decode_image(b"")


def test_float_image_is_422():
    with pytest.raises(UnprocessableError, match="float32"):
        decode_image(_png(np.zeros((8, 8), np.float32), ".tif"))


def test_pixel_limit_is_413():
    with pytest.raises(TooLargeError) as e:
        decode_image(_png(GREY8), max_pixels=40 * 60 - 1)
    _assert_sentence(e.value)
    assert decode_image(_png(GREY8), max_pixels=40 * 60).shape == (40, 60)
