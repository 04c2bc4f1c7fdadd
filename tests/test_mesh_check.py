"""builder.check_mesh: an upload's mesh decoded in a process of its own gives what decoding it here gives
(its facts, or the same error and sentence), and a process that fails says so with a 422 sentence."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.decode import inspect_mesh
from service.errors import UnprocessableError, UnsupportedMediaError
from service.jobs.build import check_mesh

IN_A_PROCESS = {"in_process_bytes": 0}  # every file, however small, goes to the checking process


def cube_stl(hole_fraction: float = 0.0) -> bytes:
    """A 60 mm cube of 192 faces as binary STL; ``hole_fraction`` of its faces removed (seeded)."""
    cube = trimesh.creation.box((60.0, 60.0, 60.0)).subdivide().subdivide()
    keep = np.random.default_rng(7).permutation(len(cube.faces))[int(round(hole_fraction * len(cube.faces))):]
    return trimesh.Trimesh(cube.vertices, cube.faces[np.sort(keep)]).export(file_type="stl")


@pytest.mark.parametrize("holes", [0.3, 0.0])
def test_a_checking_process_reports_what_decoding_here_does(holes):
    data = cube_stl(holes)
    there = check_mesh(data, "cube.stl", "cm", **IN_A_PROCESS)
    assert there == inspect_mesh(data, "cube.stl", "cm")
    assert there.extents_mm == pytest.approx((600.0, 600.0, 600.0))  # the unit reached the process
    assert there.watertight is (holes == 0.0) and (there.open_edges > 0) is (holes > 0.0)


def _nan_stl() -> bytes:
    mesh = trimesh.creation.box((10.0, 20.0, 30.0))
    vertices = np.array(mesh.vertices)
    vertices[0, 0] = np.nan
    return trimesh.Trimesh(vertices, mesh.faces, process=False).export(file_type="stl")


@pytest.mark.parametrize("data, error", [
    (_nan_stl(), UnprocessableError),  # 422: a mesh with unusable content
    (b"solid x\nfacet normal 0 0 1\n this is not an STL\n" * 4, UnsupportedMediaError),  # 415: not a mesh
])
def test_a_checking_process_refuses_as_decoding_here_does(data, error):
    with pytest.raises(error) as here:
        inspect_mesh(data, "part.stl")
    with pytest.raises(error) as there:
        check_mesh(data, "part.stl", **IN_A_PROCESS)
    assert there.value.detail == here.value.detail


def test_a_checking_process_that_runs_out_of_memory_is_a_422_sentence():
    # 1 MiB of address space: the process cannot decode anything (numpy's or OpenBLAS's allocations
    # fail, whichever comes first); the upload gets a sentence, never a 500
    with pytest.raises(UnprocessableError) as e:
        check_mesh(cube_stl(), "cube.stl", memory_mb=1, **IN_A_PROCESS)
    assert "'cube.stl'" in e.value.detail and "decimate the mesh" in e.value.detail
    assert e.value.detail.endswith(".") and "\n" not in e.value.detail
