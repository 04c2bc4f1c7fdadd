"""Uploaded bytes -> a mesh in millimetres or a grey image; bad input raises the service's errors.

Meshes: STL (binary/ASCII), OBJ, PLY, OFF, GLB, read by trimesh; scenes are merged into one mesh;
the declared unit is converted to mm here, once. Non-watertight meshes are fine.
Images: PNG, JPEG, BMP, TIFF, 8- or 16-bit, grey or colour, read by OpenCV; colour stays BGR (the
verdict reads it), alpha is dropped.

Errors: a format we do not read or bytes that are not one -> ``UnsupportedMediaError`` (415); a file
that is empty, truncated, or holds an unusable mesh/image -> ``UnprocessableError`` (422); an image
over the pixel limit -> ``TooLargeError`` (413).
"""

from __future__ import annotations

import io
import warnings
from pathlib import PurePath

import cv2
import numpy as np
import trimesh
from PIL import Image

from service.errors import TooLargeError, UnprocessableError, UnsupportedMediaError, clause

MESH_FORMATS = ("stl", "obj", "ply", "off", "glb")
UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
MAX_MESH_FACES = 2_000_000  # a 100 MB binary STL holds ~2M triangles; more only slows the build


def mesh_format(filename: str) -> str:
    """The mesh format from the file name's extension; 415 if it is not one we read."""
    ext = PurePath(filename or "").suffix.lower().lstrip(".")
    if ext not in MESH_FORMATS:
        got = f"'.{ext}'" if ext else "no extension"
        raise UnsupportedMediaError(f"The mesh file name '{filename}' has {got}; upload an STL, OBJ, PLY, "
                                    "OFF or GLB file with the matching extension")
    return ext


def decode_mesh(data: bytes, filename: str, units: str = "mm") -> trimesh.Trimesh:
    """Mesh file bytes -> one ``trimesh.Trimesh``, vertices in mm (object frame), merged and processed."""
    if units not in UNIT_TO_MM:
        raise UnprocessableError(f"The unit '{units}' is not one of mm, cm, m, in; declare the mesh's unit "
                                 "with one of them")
    ext = mesh_format(filename)
    if not data:
        raise UnprocessableError(f"The mesh file '{filename}' is empty; upload the whole file")
    what = f"The file '{filename}' is not a readable {ext.upper()} mesh"
    try:
        loaded = trimesh.load(file_obj=io.BytesIO(data), file_type=ext, process=False)
    except Exception as e:  # trimesh raises anything from ValueError to struct.error on bad bytes
        raise UnsupportedMediaError(f"{what} ({clause(e) or type(e).__name__}); check the file is complete "
                                    "and in that format") from e
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
    if np.count_nonzero(mesh.extents > 0) < 2:
        size = np.round(mesh.extents, 6).tolist()
        raise UnprocessableError(f"The mesh in '{filename}' has zero extent (size {size} mm); upload a mesh "
                                 "that spans a surface")
    return mesh


# --- images ----------------------------------------------------------------------------------------

_FORMATS = "PNG, JPEG, BMP or TIFF"


def _truncated(data: bytes) -> str | None:
    """The format name if the bytes are a PNG/JPEG cut short (OpenCV would half-decode those)."""
    if data.startswith(b"\x89PNG\r\n\x1a\n") and b"IEND" not in data[-64:]:
        return "PNG"
    if data.startswith(b"\xff\xd8") and b"\xff\xd9" not in data[-4096:]:
        return "JPEG"
    return None


def image_size(data: bytes) -> tuple[int, int] | None:
    """(w, h) from the file header, without decoding pixels; None if PIL cannot tell."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data)) as im:
                return int(im.size[0]), int(im.size[1])
    except Image.DecompressionBombError:
        return None  # OpenCV's own limit or ours below will catch it
    except Exception:
        return None


def decode_image(data: bytes, *, max_pixels: int | None = None) -> np.ndarray:
    """Image file bytes -> grey (H, W) or BGR (H, W, 3), uint8 or uint16 (shape is (h, w); the API says
    (w, h))."""
    if not data:
        raise UnprocessableError("The image file is empty; upload the whole image")
    size = image_size(data)
    if size is not None and max_pixels is not None and size[0] * size[1] > max_pixels:
        raise TooLargeError(f"The image is {size[0]} x {size[1]} = {size[0] * size[1]:,} pixels, more than "
                            f"the limit of {max_pixels:,}; send a smaller image")
    fmt = _truncated(data)
    if fmt is not None:
        raise UnprocessableError(f"The {fmt} image is truncated (its end is missing); upload the whole file")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if (img is None or img.size == 0) and size is not None:
        raise UnprocessableError(f"The image header says {size[0]} x {size[1]} pixels but the pixels could "
                                 "not be decoded (truncated or damaged file); upload the whole file")
    if img is None or img.size == 0:
        raise UnsupportedMediaError(f"The image could not be decoded; upload a {_FORMATS} file")
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
    if max_pixels is not None and img.shape[0] * img.shape[1] > max_pixels:
        raise TooLargeError(f"The image is {img.shape[1]} x {img.shape[0]} pixels, more than the limit of "
                       f"{max_pixels:,}; send a smaller image")
    return np.ascontiguousarray(img)
