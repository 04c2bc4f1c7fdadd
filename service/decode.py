"""Uploaded bytes -> a mesh in millimetres or a grey image; bad input raises the service's errors.

Meshes: STL (binary/ASCII), OBJ, PLY, OFF, GLB, read by trimesh; scenes are merged into one mesh;
the declared unit is converted to mm here, once. Non-watertight meshes are accepted; ``mesh_facts``
counts their open edges so that the upload can warn (a hole shows in silhouettes). The format is the
file name's extension, or, when the name has none we read, what the bytes are (``sniff_mesh``).
A mesh must span a surface: at least ``MIN_MESH_FACES`` faces, a non-zero area, and a largest side
of at least ``MIN_MESH_EXTENT_MM``. Builds render at most ``TEMPLATE_FACE_BUDGET`` faces: a larger
mesh is simplified to it first (``fit_face_budget``; ``bench/mesh_budget.py`` measures the cost).
Images: PNG, JPEG, BMP, TIFF, 8- or 16-bit, grey or colour, read by OpenCV; colour stays BGR (the
verdict reads it), alpha is dropped. Their
size is read from the file header (``image_header``) and checked against the pixel limit and the
minimum size BEFORE a pixel is decoded; any other format is refused unread.

Errors: a format we do not read or bytes that are not one -> ``UnsupportedMediaError`` (415); a file
that is empty, truncated, or holds an unusable mesh/image -> ``UnprocessableError`` (422); an image
over the pixel limit -> ``TooLargeError`` (413).
"""

from __future__ import annotations

import io
import re
import struct
import threading
from dataclasses import dataclass
from pathlib import PurePath

import cv2
import numpy as np
import trimesh

from service.errors import TooLargeError, UnprocessableError, UnsupportedMediaError, clause

MESH_FORMATS = ("stl", "obj", "ply", "off", "glb")
UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
MAX_MESH_FACES = 2_000_000  # a 100 MB binary STL holds ~2M triangles; more only slows the build
MIN_MESH_FACES = 4  # fewer cannot enclose anything: a stray triangle or two is not a part
MIN_MESH_AREA_MM2 = 1e-6  # total surface area, mm^2, after the unit conversion
MIN_MESH_EXTENT_MM = 1.0  # the mesh's largest side, mm: smaller is a unit mistake or a speck
# Thinnest extent (along the vertices' least principal axis) as a fraction of the largest: under
# this a part seen edge-on is a line thinner than a template pixel (render_px 400 spans the part),
# a template that fits any straight edge in any image with full confidence.
MIN_THICKNESS_FRACTION = 1.0 / 400.0
# Template builds rasterise the mesh ~1,000 times at render_px (400 px across the part, 2x
# supersampled); their memory and time grow with the face count. A silhouette at that resolution
# needs far fewer faces than a fine CAD export has: meshes over this budget are simplified to it
# before the build. bench/mesh_budget.py measures what that costs (see the README).
TEMPLATE_FACE_BUDGET = 20_000
_MESH_DECODES = threading.BoundedSemaphore(1)  # one large mesh decoded at a time per process (~1.4 GB peak)
_STL_BINARY_HEADER = 84
_STL_BINARY_FACE = 50


def _sniff_stl_binary(data: bytes) -> bool:
    if len(data) < _STL_BINARY_HEADER:
        return False
    (n,) = struct.unpack_from("<I", data, 80)
    return len(data) == _STL_BINARY_HEADER + _STL_BINARY_FACE * n and n > 0


def _text_head(data: bytes, n: int = 4096) -> str:
    return data[:n].decode("latin-1").lstrip().lower()


def sniff_mesh(data: bytes) -> str | None:
    """The mesh format the bytes themselves show (one of ``MESH_FORMATS``), or None."""
    if data.startswith(b"glTF"):
        return "glb"
    head = _text_head(data)
    if head.startswith("ply"):
        return "ply"
    if re.match(r"[cn]?off\b", head):
        return "off"
    if _sniff_stl_binary(data) or (head.startswith("solid") and "facet" in head):
        return "stl"
    if re.search(r"^v\s", head, re.M) and re.search(r"^f\s", _text_head(data, 1 << 20), re.M):
        return "obj"
    return None


def mesh_format(filename: str, data: bytes | None = None) -> str:
    """The mesh format from the file name's extension, else from the content; 415 if neither is one
    we read."""
    ext = PurePath(filename or "").suffix.lower().lstrip(".")
    if ext in MESH_FORMATS:
        return ext
    sniffed = sniff_mesh(data) if data else None
    if sniffed is not None:
        return sniffed
    got = f"the extension '.{ext}'" if ext else "no extension"
    raise UnsupportedMediaError(f"The mesh file '{_short(filename)}' has {got} and its content is not an "
                                "STL, OBJ, PLY, OFF or GLB mesh; upload one of those formats")


def _short(text: str, n: int = 80) -> str:
    """``text`` cut to ``n`` characters for echoing in a detail."""
    return text if len(text) <= n else text[: n - 3] + "..."


def _check_stl(data: bytes, filename: str) -> None:
    """415 with what is wrong when the bytes are neither a complete binary STL nor ASCII STL text."""
    if _sniff_stl_binary(data):
        return
    head = _text_head(data)
    if head.startswith("solid") and "facet" in _text_head(data, 1 << 16) and b"\0" not in data[:4096]:
        return  # ASCII STL: trimesh parses it (and says where it is broken)
    name = _short(filename)
    if len(data) < _STL_BINARY_HEADER:
        raise UnsupportedMediaError(f"The file '{name}' is not an STL mesh: it has only {len(data)} bytes, "
                                    "less than a binary STL header, and is not ASCII STL text; upload the "
                                    "whole file")
    (n,) = struct.unpack_from("<I", data, 80)
    need = _STL_BINARY_HEADER + _STL_BINARY_FACE * n
    raise UnsupportedMediaError(
        f"The file '{name}' is not a readable STL mesh: as a binary STL its header announces {n:,} "
        f"triangles, which take {need:,} bytes, but the file has {len(data):,} bytes, and it is not ASCII "
        "STL text ('solid ... facet ...'); upload the complete, unmodified file")


def decode_mesh(data: bytes, filename: str, units: str = "mm") -> trimesh.Trimesh:
    """Mesh file bytes -> one ``trimesh.Trimesh``, vertices in mm (object frame), merged and processed."""
    if units not in UNIT_TO_MM:
        raise UnprocessableError(f"The unit '{units}' is not one of mm, cm, m, in; declare the mesh's unit "
                                 "with one of them")
    if not data:
        raise UnprocessableError(f"The mesh file '{_short(filename)}' is empty; upload the whole file")
    ext = mesh_format(filename, data)
    filename = _short(filename)
    if ext == "stl":
        _check_stl(data, filename)
    what = f"The file '{filename}' is not a readable {ext.upper()} mesh"
    try:
        with _MESH_DECODES:
            return _decode_mesh(data, filename, ext, units)
    except (ImportError, MemoryError, OSError) as e:  # about this service, not the file: no detail to show
        raise UnsupportedMediaError(f"{what}; check the file is complete and in that format") from e
    except (UnsupportedMediaError, UnprocessableError):
        raise
    except Exception as e:  # trimesh raises anything from ValueError to struct.error on bad bytes
        raise UnsupportedMediaError(f"{what} ({clause(e) or type(e).__name__}); check the file is complete "
                                    "and in that format") from e


def _decode_mesh(data: bytes, filename: str, ext: str, units: str) -> trimesh.Trimesh:
    what = f"The file '{filename}' is not a readable {ext.upper()} mesh"
    loaded = trimesh.load(file_obj=io.BytesIO(data), file_type=ext, process=False)
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        loaded = trimesh.util.concatenate(meshes) if meshes else None
    if isinstance(loaded, trimesh.PointCloud):
        raise UnprocessableError(f"The file '{filename}' holds a point cloud without faces; upload a surface "
                                 "mesh")
    if not isinstance(loaded, trimesh.Trimesh):
        raise UnsupportedMediaError(f"{what} (it holds no triangle mesh); upload a file with a surface mesh "
                                    "in it")
    vertices = np.asarray(loaded.vertices, np.float64)
    faces = np.asarray(loaded.faces, np.int64)
    if len(faces) == 0:
        raise UnprocessableError(f"The mesh in '{filename}' has no faces; upload a surface mesh, not a point "
                                 "cloud")
    if len(faces) > MAX_MESH_FACES:
        raise UnprocessableError(f"The mesh in '{filename}' has {len(faces):,} faces, more than the limit of "
                                 f"{MAX_MESH_FACES:,}; decimate it first")
    if not np.isfinite(vertices).all():
        raise UnprocessableError(f"The mesh in '{filename}' has NaN or infinite vertex coordinates; repair "
                                 "the file")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise UnprocessableError(f"The mesh in '{filename}' has faces that index missing vertices; repair "
                                 "the file")
    mesh = trimesh.Trimesh(vertices=vertices * UNIT_TO_MM[units], faces=faces, process=True)
    check_geometry(mesh, filename, units)
    return mesh


@dataclass(frozen=True)
class MeshFacts:
    """What an upload records about its mesh: ``extents_mm`` (3,) bounding-box sides, mm, object frame;
    ``open_edges``: edges of one face only (the rims of holes); ``nonmanifold_edges``: edges joining
    more than two faces. Counted over the distinct faces: a face given twice (a double-sided export,
    as T-LESS's models are) closes no hole and opens none."""

    extents_mm: tuple[float, float, float]
    open_edges: int
    nonmanifold_edges: int

    @property
    def watertight(self) -> bool:
        """Every edge joins exactly two faces (trimesh's ``is_watertight`` on the distinct faces)."""
        return self.open_edges == 0 and self.nonmanifold_edges == 0


def mesh_facts(mesh: trimesh.Trimesh) -> MeshFacts:
    """``MeshFacts`` of a decoded mesh (its duplicate vertices already merged by ``decode_mesh``)."""
    faces = np.asarray(mesh.faces, np.int64)
    distinct = faces[trimesh.grouping.unique_rows(np.sort(faces, axis=1))[0]]
    edges = np.sort(distinct[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    # one int64 key per edge: vertex counts stay far below 3e9 (MAX_MESH_FACES bounds them)
    _, uses = np.unique(edges[:, 0] * (int(edges.max()) + 1) + edges[:, 1], return_counts=True)
    ext = [float(x) for x in mesh.extents]
    return MeshFacts((ext[0], ext[1], ext[2]), open_edges=int(np.count_nonzero(uses == 1)),
                     nonmanifold_edges=int(np.count_nonzero(uses > 2)))


def inspect_mesh(data: bytes, filename: str, units: str = "mm") -> MeshFacts:
    """``decode_mesh`` (its 415/422 on bad bytes), then what an upload records about the mesh."""
    return mesh_facts(decode_mesh(data, filename, units))


def check_geometry(mesh: trimesh.Trimesh, filename: str, units: str = "mm") -> None:
    """422 for a mesh that cannot be a part: no extent, fewer than ``MIN_MESH_FACES`` faces, no area,
    or smaller than ``MIN_MESH_EXTENT_MM`` (a template bank of it would match anything or nothing)."""
    size = [float(f"{x:.3g}") for x in np.asarray(mesh.extents, float)]
    if np.count_nonzero(mesh.extents > 0) < 2:
        raise UnprocessableError(f"The mesh in '{filename}' has zero extent (size {size} mm); upload a mesh "
                                 "that spans a surface")
    if len(mesh.faces) < MIN_MESH_FACES:
        raise UnprocessableError(f"The mesh in '{filename}' has {len(mesh.faces)} non-degenerate face"
                                 f"{'s' if len(mesh.faces) != 1 else ''}, fewer than {MIN_MESH_FACES}; "
                                 "upload the part's whole surface mesh")
    area = float(mesh.area)
    if not area > MIN_MESH_AREA_MM2:
        raise UnprocessableError(f"The mesh in '{filename}' has a surface area of {area:.3g} mm^2 (its "
                                 "triangles are degenerate); upload a mesh whose faces span a surface")
    largest = float(np.max(mesh.extents))
    V = np.asarray(mesh.vertices, np.float64)
    centred = V - V.mean(axis=0)
    thinnest = np.linalg.eigh(centred.T @ centred)[1][:, 0]  # least principal axis
    thickness = float(np.ptp(centred @ thinnest))
    if thickness < MIN_THICKNESS_FRACTION * largest:
        raise UnprocessableError(f"The mesh in '{filename}' is flat or thin ({thickness:.3g} mm thick across "
                                 f"{largest:.3g} mm): seen edge-on it is a line that would match any "
                                 "straight edge; upload the part as a solid with its real thickness")
    if largest < MIN_MESH_EXTENT_MM:
        bigger = [u for u, k in UNIT_TO_MM.items() if k > UNIT_TO_MM.get(units, 1.0)]
        hint = f"; if its coordinates are in {' or '.join(bigger)}, declare that with units" if bigger else ""
        raise UnprocessableError(f"The mesh in '{filename}' is only {largest:.3g} mm across (size {size} "
                                 f"mm), under the minimum of {MIN_MESH_EXTENT_MM:g} mm{hint}; or upload the "
                                 "part at its real size")


def fit_face_budget(mesh: trimesh.Trimesh, max_faces: int = TEMPLATE_FACE_BUDGET) -> trimesh.Trimesh:
    """``mesh`` itself if it has at most ``max_faces`` faces, else a simplification of it with at most that
    many (vertices in the same frame and unit; ``bench/mesh_budget.py`` measures how far the silhouette
    moves): quadric decimation; where that stalls above the budget (fans of sliver triangles, as at a
    UV sphere's poles), the vertices are first merged on a grid of 1/2000 of the part's size (0.2
    template pixels) and decimated again; clustering on coarser grids is the last resort."""
    if len(mesh.faces) <= max_faces:
        return mesh
    from fast_simplification import simplify

    V0, F0 = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    V, F = simplify(points=V0, triangles=F0, target_count=int(max_faces))
    cell = float(np.max(np.ptp(V0, axis=0))) / 2000.0
    if len(F) > max_faces:
        V, F = simplify(*_cluster_vertices(V0, F0, cell), target_count=int(max_faces))
    while len(F) > max_faces:
        cell *= 2.0
        V, F = _cluster_vertices(V, F, cell)
    return trimesh.Trimesh(vertices=V, faces=F, process=True)


def _cluster_vertices(V: np.ndarray, F: np.ndarray, cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge the vertices in each ``cell_mm`` grid cell into their mean; drop the faces that collapse."""
    keys = np.floor((V - V.min(axis=0)) / cell_mm).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, inverse, V)
    merged /= counts[:, None]
    F = inverse[F]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    return merged, F[np.sort(first)]


# --- images ----------------------------------------------------------------------------------------

_FORMATS = "PNG, JPEG, BMP or TIFF"


def _truncated(data: bytes) -> str | None:
    """The format name if the bytes are a PNG/JPEG cut short (OpenCV would half-decode those)."""
    if data.startswith(b"\x89PNG\r\n\x1a\n") and b"IEND" not in data[-64:]:
        return "PNG"
    if data.startswith(b"\xff\xd8") and b"\xff\xd9" not in data[-4096:]:
        return "JPEG"
    return None


MIN_IMAGE_SIDE_PX = 32  # edges run at half size and the coarse search pools that by 8 again


class _HeaderError(ValueError):
    """The bytes start like one of our formats but its header is cut short or damaged."""


def _u(fmt: str, data: bytes, offset: int) -> tuple:
    try:
        return struct.unpack_from(fmt, data, offset)
    except struct.error as e:
        raise _HeaderError("the header is cut short") from e


def _png_size(data: bytes) -> tuple[int, int]:
    if data[12:16] != b"IHDR":
        raise _HeaderError("the first chunk is not IHDR")
    return _u(">II", data, 16)


# Start-of-frame markers: every SOFn but DHT (C4), JPG (C8) and DAC (CC)
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(data: bytes) -> tuple[int, int]:
    pos = 2
    while True:
        while pos < len(data) and data[pos] != 0xFF:  # tolerate junk between segments, as decoders do
            pos += 1
        while pos < len(data) and data[pos] == 0xFF:
            pos += 1
        if pos >= len(data):
            raise _HeaderError("no frame header (SOF) before the end of the file")
        marker = data[pos]
        pos += 1
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            continue
        if marker in (0xD9, 0xDA):
            raise _HeaderError("the scan starts before any frame header (SOF)")
        (length,) = _u(">H", data, pos)
        if marker in _JPEG_SOF:
            h, w = _u(">HH", data, pos + 3)
            return w, h
        pos += length


def _bmp_size(data: bytes) -> tuple[int, int]:
    (dib,) = _u("<I", data, 14)
    if dib == 12:  # BITMAPCOREHEADER
        return _u("<HH", data, 18)
    w, h = _u("<ii", data, 18)
    return w, abs(h)  # a negative height means rows stored top-down


_TIFF_TYPES = {3: "H", 4: "I", 16: "Q"}  # SHORT, LONG, LONG8


def _tiff_size(data: bytes) -> tuple[int, int]:
    e = "<" if data[:2] == b"II" else ">"
    (version,) = _u(e + "H", data, 2)
    if version == 42:
        (ifd,) = _u(e + "I", data, 4)
        (n,) = _u(e + "H", data, ifd)
        entries, size, first = ifd + 2, 12, 8
    else:  # BigTIFF
        (ifd,) = _u(e + "Q", data, 8)
        (n,) = _u(e + "Q", data, ifd)
        entries, size, first = ifd + 8, 20, 12
    found: dict[int, int] = {}
    for k in range(min(int(n), 4096)):
        at = entries + k * size
        tag, typ = _u(e + "HH", data, at)
        if tag in (256, 257) and typ in _TIFF_TYPES:
            (found[tag],) = _u(e + _TIFF_TYPES[typ], data, at + first)
    if 256 not in found or 257 not in found:
        raise _HeaderError("the first image directory has no width or height")
    return found[256], found[257]


_IMAGE_FORMATS = (  # (name, magic bytes, header reader)
    ("PNG", (b"\x89PNG\r\n\x1a\n",), _png_size),
    ("JPEG", (b"\xff\xd8\xff",), _jpeg_size),
    ("BMP", (b"BM",), _bmp_size),
    ("TIFF", (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"), _tiff_size),
)


def image_header(data: bytes) -> tuple[str, int, int]:
    """(format, w, h) from the file header alone, without decoding a pixel.

    415 if the bytes are not PNG, JPEG, BMP or TIFF; 422 if the header is cut short or damaged.
    """
    for name, magics, reader in _IMAGE_FORMATS:
        if data.startswith(magics):
            try:
                w, h = reader(data)
            except _HeaderError as e:
                raise UnprocessableError(f"The {name} image's header is damaged ({clause(e)}); upload the "
                                         "whole, unmodified file") from e
            return name, int(w), int(h)
    raise UnsupportedMediaError(f"The image is not a {_FORMATS} file (its first bytes are {data[:8]!r}); "
                                "send the image in one of those formats")


def image_size(data: bytes) -> tuple[int, int] | None:
    """(w, h) from the file header, without decoding pixels; None if it is not one of our formats."""
    try:
        _, w, h = image_header(data)
    except (UnsupportedMediaError, UnprocessableError):
        return None
    return w, h


def decode_image(data: bytes, *, max_pixels: int | None = None) -> np.ndarray:
    """Image file bytes -> grey (H, W) or BGR (H, W, 3), uint8 or uint16 (shape is (h, w); the API
    says (w, h)).

    The size is read from the header and checked (over ``max_pixels``: 413; a side under
    ``MIN_IMAGE_SIDE_PX``: 422) before any pixel is decoded, so an image bomb costs nothing.
    """
    if not data:
        raise UnprocessableError("The image file is empty; upload the whole image")
    fmt, w, h = image_header(data)
    if max_pixels is not None and w * h > max_pixels:
        raise TooLargeError(f"The image is {w} x {h} = {w * h:,} pixels, more than the limit of "
                            f"{max_pixels:,} (POSE_MAX_IMAGE_PIXELS); send a smaller image")
    if min(w, h) < MIN_IMAGE_SIDE_PX:
        raise UnprocessableError(f"The image is {w} x {h} pixels, but both sides must be at least "
                                 f"{MIN_IMAGE_SIDE_PX} pixels; send the camera's full frame")
    truncated = _truncated(data)
    if truncated is not None:
        raise UnprocessableError(f"The {truncated} image is truncated (its end is missing); upload the whole "
                                 "file")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # OpenCV's own limits, or a decoder giving up half way
        raise UnprocessableError(f"The {fmt} image ({w} x {h} pixels by its header) could not be decoded "
                                 "(damaged or unsupported variant); re-save it as a plain 8- or 16-bit "
                                 f"{_FORMATS} file") from e
    if img is None or img.size == 0:
        raise UnprocessableError(f"The {fmt} header says {w} x {h} pixels but the pixels could not be "
                                 "decoded (truncated or damaged file); upload the whole file")
    if img.dtype not in (np.uint8, np.uint16):
        raise UnprocessableError(f"The image has {img.dtype} pixels; send an 8- or 16-bit {_FORMATS} image")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    elif img.ndim == 3 and img.shape[2] == 2:
        img = img[:, :, 0]  # grey + alpha
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]  # colour is evidence for the verdict; alpha is not
    if img.ndim != 2 and not (img.ndim == 3 and img.shape[2] == 3):
        raise UnprocessableError(f"The image has an unsupported shape {img.shape}; send a grey or colour "
                                 "image")
    if (img.shape[1], img.shape[0]) != (w, h):  # the header lied: hold the decoded image to the limits too
        if max_pixels is not None and img.size > max_pixels:
            raise TooLargeError(f"The image is {img.shape[1]} x {img.shape[0]} pixels, more than the limit "
                                f"of {max_pixels:,} (POSE_MAX_IMAGE_PIXELS); send a smaller image")
        if min(img.shape) < MIN_IMAGE_SIDE_PX:
            raise UnprocessableError(f"The image is {img.shape[1]} x {img.shape[0]} pixels, but both sides "
                                     f"must be at least {MIN_IMAGE_SIDE_PX} pixels; send the camera's full "
                                     "frame")
    return np.ascontiguousarray(img)
