"""decode: every accepted mesh/image format, unit conversion, and each kind of bad file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from service import decode
from service.decode import decode_image, decode_mesh, inspect_mesh
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


def test_mesh_facts_count_the_rims_of_holes_across_the_files_duplicate_vertices():
    # STL repeats every vertex per face: the edges only meet once decode_mesh has merged them
    closed = inspect_mesh(_export(_box(), "stl"), "box.stl")
    assert closed.watertight and closed.open_edges == closed.nonmanifold_edges == 0
    assert closed.extents_mm == pytest.approx((10.0, 20.0, 30.0))
    box = _box()
    holed = inspect_mesh(_export(trimesh.Trimesh(box.vertices, box.faces[:-2]), "stl"), "open.stl")
    assert not holed.watertight
    assert holed.open_edges == 4 and holed.nonmanifold_edges == 0  # one square side gone: its 4 sides open


def test_a_double_sided_export_is_closed_and_three_faces_on_an_edge_are_not():
    box = _box()
    both_sides = trimesh.Trimesh(box.vertices, np.vstack([box.faces, box.faces[:, ::-1]]), process=False)
    assert not both_sides.is_watertight  # trimesh counts each edge 4 times ...
    assert decode.mesh_facts(both_sides).watertight  # ... but no hole opens in a silhouette (T-LESS's models)
    fin = trimesh.Trimesh(np.vstack([box.vertices, [[0.0, 0.0, 40.0]]]),
                          np.vstack([box.faces, [[*box.edges_unique[0], 8]]]), process=False)
    facts = decode.mesh_facts(fin)  # a fin on one of the box's edges: 3 faces there, 2 open edges
    assert not facts.watertight and facts.nonmanifold_edges == 1 and facts.open_edges == 2


@pytest.mark.parametrize("filename", ["part.step", "part", "part.stl.txt"])
def test_unknown_extension_with_no_mesh_inside_is_415(filename):
    with pytest.raises(UnsupportedMediaError) as e:
        decode_mesh(b"ISO-10303-21;\nHEADER;\n" * 10, filename)
    _assert_sentence(e.value)
    assert "STL, OBJ, PLY, OFF or GLB" in e.value.detail


@pytest.mark.parametrize("file_type", ["stl", "stl_ascii", "obj", "ply", "off", "glb"])
@pytest.mark.parametrize("filename", ["part", "part.bin", "upload.stl.txt"])
def test_a_name_without_a_mesh_extension_is_read_by_content(file_type, filename):
    """Issue item 12: the content tells the format when the file name does not."""
    mesh = decode_mesh(_export(_box(), file_type), filename)
    np.testing.assert_allclose(mesh.extents, [10.0, 20.0, 30.0], atol=1e-6)


@pytest.mark.parametrize("data", [b"\x00" * 100, b"\x00" * 80 + (1000).to_bytes(4, "little") + b"\x01" * 500,
                                  b"\x07" * 40])
def test_unreadable_binary_stl_says_what_is_wrong_with_the_file(monkeypatch, data):
    """Issue item 9: the detail is about the file (its size against its triangle count), never about the
    service's modules (trimesh's ASCII fallback imports charset_normalizer, absent from slim images)."""
    import sys

    monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # as in an image without it
    with pytest.raises(UnsupportedMediaError) as e:
        decode_mesh(data, "part.stl")
    _assert_sentence(e.value)
    assert "module" not in e.value.detail and "charset" not in e.value.detail
    assert "STL" in e.value.detail and "bytes" in e.value.detail


@pytest.mark.parametrize("mesh, words", [
    (trimesh.Trimesh([[0, 0, 0], [1e-6, 0, 0], [0, 1e-6, 0]], [[0, 1, 2]], process=False), "fewer than 4"),
    (trimesh.Trimesh([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], [[0, 1, 2], [1, 3, 2]], process=False),
     "fewer than 4"),
    (trimesh.creation.box((0.5, 0.4, 0.3)), "under the minimum of 1 mm"),
    (trimesh.creation.icosphere(radius=0.2), "under the minimum of 1 mm"),
])
def test_degenerate_meshes_are_refused_with_a_sentence(mesh, words):
    """Issue item 7: a mesh that cannot be a part (a 1e-6 mm triangle, two triangles, a speck) fails at
    upload instead of building a bank that fails every estimate."""
    with pytest.raises(UnprocessableError, match=words) as e:
        decode_mesh(_export(mesh, "stl"), "tiny.stl")
    _assert_sentence(e.value)


def test_a_part_in_metres_declared_as_mm_gets_the_units_hint():
    with pytest.raises(UnprocessableError, match="units") as e:
        decode_mesh(_export(trimesh.creation.box((0.06, 0.2, 0.06)), "stl"), "sprayer_in_m.stl")
    assert "cm or m or in" in e.value.detail
    in_m = decode_mesh(_export(trimesh.creation.box((0.06, 0.2, 0.06)), "stl"), "s.stl", "m")
    assert in_m.extents[1] == pytest.approx(200)


def test_face_budget_simplifies_large_meshes_and_keeps_small_ones():
    """Issue item 1: builds get at most TEMPLATE_FACE_BUDGET faces; the shape stays where it was."""
    small = trimesh.creation.icosphere(subdivisions=3, radius=50.0)  # 1,280 faces
    assert decode.fit_face_budget(small, 2000) is small
    big = trimesh.creation.uv_sphere(50.0, count=[120, 120])  # ~28,000 faces
    fitted = decode.fit_face_budget(big, 2000)
    assert 500 < len(fitted.faces) <= 2000
    radii = np.linalg.norm(fitted.vertices, axis=1)
    assert np.abs(radii - 50.0).max() < 0.5  # vertices stay on the sphere (within 1 %)
    np.testing.assert_allclose(fitted.extents, big.extents, rtol=0.01)


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
        decode_image(_png(np.zeros((40, 40), np.float32), ".tif"))


def test_pixel_limit_is_413():
    with pytest.raises(TooLargeError) as e:
        decode_image(_png(GREY8), max_pixels=40 * 60 - 1)
    _assert_sentence(e.value)
    assert decode_image(_png(GREY8), max_pixels=40 * 60).shape == (40, 60)


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tif"])
@pytest.mark.parametrize("w, h", [(60, 40), (1, 1), (5000, 1), (33, 700)])
def test_header_size_is_read_for_every_accepted_format(ext, w, h):
    img = np.full((h, w, 3), 128, np.uint8)
    assert decode.image_header(_png(img, ext))[1:] == (w, h)


def _png_header_only(w: int, h: int) -> bytes:
    """A PNG whose IHDR says w x h over a tiny, valid-looking rest (an image bomb's header)."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = lambda kind, body: (struct.pack(">I", len(body)) + kind + body  # noqa: E731
                                + struct.pack(">I", zlib.crc32(kind + body)))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + \
        chunk(b"IEND", b"")


def test_image_bomb_is_refused_from_its_header_before_decoding(monkeypatch):
    """Issue item 3: a 20000 x 20000 PNG is refused by its header; OpenCV is never asked to decode it."""
    def no_decoding(*a, **k):
        raise AssertionError("decoded before the size check")

    monkeypatch.setattr(decode.cv2, "imdecode", no_decoding)
    with pytest.raises(TooLargeError, match="20000 x 20000") as e:
        decode_image(_png_header_only(20000, 20000), max_pixels=50_000_000)
    _assert_sentence(e.value)
    big = np.zeros((60, 40), np.uint8)
    for ext in (".jpg", ".bmp", ".tif"):
        with pytest.raises(TooLargeError):
            decode_image(_png(big, ext), max_pixels=40 * 60 - 1)


def test_over_opencvs_own_pixel_limit_is_not_a_500():
    """Issue item 4: OpenCV's imdecode raises over its own limit (2^30 pixels): with a service limit
    above that, the answer is a 422 sentence, not an exception; with the default limit, a 413."""
    bomb = _png_header_only(40000, 30000)
    with pytest.raises(UnprocessableError) as e:
        decode_image(bomb, max_pixels=2_000_000_000)
    _assert_sentence(e.value)
    with pytest.raises(TooLargeError):
        decode_image(bomb, max_pixels=50_000_000)


@pytest.mark.parametrize("w, h", [(1, 1), (1, 5000), (5000, 1), (31, 480)])
def test_tiny_images_are_422_with_the_minimum(w, h):
    """Issue item 4: 1x1 and 1x5000 images made edges.py's cv2.resize fail (500)."""
    with pytest.raises(UnprocessableError, match=f"at least {decode.MIN_IMAGE_SIDE_PX} pixels") as e:
        decode_image(_png(np.zeros((h, w), np.uint8)))
    _assert_sentence(e.value)


def test_other_formats_are_refused_unread():
    ok, pgm = cv2.imencode(".pgm", np.zeros((40, 60), np.uint8))
    with pytest.raises(UnsupportedMediaError, match="PNG, JPEG, BMP or TIFF"):
        decode_image(pgm.tobytes())
