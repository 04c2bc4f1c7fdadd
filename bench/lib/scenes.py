"""The test part of the rendered-scene benchmarks (``bench/instances.py``, ``bench/plane.py``)."""

from __future__ import annotations

import trimesh


def l_block() -> trimesh.Trimesh:
    """An L-shaped block, 80 x 60 x 40 mm, arms of unequal length: no symmetry."""
    a = trimesh.creation.box((80.0, 20.0, 40.0))
    b = trimesh.creation.box((20.0, 40.0, 40.0))
    b.apply_translation((-30.0, 30.0, 0.0))
    return trimesh.util.concatenate([a, b])


# the coarse template grid the rendered-scene benchmarks build the block's bank on
L_BLOCK_GRID = {"view_step_deg": 15.0, "render_px": 160}


def l_block_bank():
    """The block's template bank (``L_BLOCK_GRID``, no symmetry)."""
    from service.vision.pipeline import build_templates

    return build_templates(l_block(), symmetry="none", grid=L_BLOCK_GRID)
