"""One estimate of a small synthetic scene, so a fresh process loads or compiles its numba kernels and
maps its big buffers before the first real frame."""

from __future__ import annotations

import numpy as np
import trimesh

from service.vision import memory
from service.vision.deadline import timing_paused
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx
from service.vision.geometry.plane import Plane
from service.vision.pipeline.build import build_templates
from service.vision.pipeline.estimate import estimate
from service.vision.pipeline.types import EstimateOutput

WARM_UP_POSE = Pose(Rx(60.0), np.array([5.0, -4.0, 300.0]))  # a cylinder, slightly off the optical axis
WARM_UP_TABLE = Plane(np.array([0.0, 0.0, -1.0]), -330.0)  # a table behind it, facing the camera
# A frame the size of a cell camera's: the first real frame then finds its big buffers' memory already
# mapped (at 320 x 240 the first 1280 x 960 frame still cost twice a warm one).
WARM_UP_SIZE = (1280, 960)


def warm_up() -> EstimateOutput:
    """Run the whole pipeline once on a cylinder rendered 300 mm away (~0.5 s). Returns the estimate of
    the rendered cylinder (its known answer: ``WARM_UP_POSE``)."""
    with timing_paused():  # its durations are kernel compiles: no frame's time budget learns from them
        return _warm_up()


def _warm_up() -> EstimateOutput:
    from service.vision.geometry.render import render_shaded

    memory.keep_mapped()  # the warm-up's freed buffers stay mapped for the first real frame
    mesh = trimesh.creation.cylinder(radius=20.0, height=60.0, sections=24)
    bank = build_templates(mesh, symmetry="auto", grid={"view_step_deg": 30.0, "tilt_step_deg": 15.0,
                                                        "render_px": 96})
    intr = Intrinsics(1200.0, 1200.0, 639.5, 479.5)
    img = render_shaded(bank.vertices_mm, bank.faces, WARM_UP_POSE, intr.K, WARM_UP_SIZE)
    estimate(bank, img, intr)  # the unknown-distance path has kernels of its own
    estimate(bank, img, intr, plane=WARM_UP_TABLE)  # and the plane's gradient search
    out = estimate(bank, img, intr, distance_mm=float(WARM_UP_POSE.t_mm[2]))
    memory.keep_mapped(memory.RESERVE_MB)  # with room for what is loaded after it
    return out
