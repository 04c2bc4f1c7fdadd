"""The upload's pipeline: a mesh in mm -> its template bank, and a picture of one template."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from service.vision import threads
from service.vision.bank import TemplateBank


def build_templates(mesh: trimesh.Trimesh, *, symmetry: str = "auto", grid: dict | None = None,
                    progress: Callable[[float], None] | None = None) -> TemplateBank:
    """Mesh in mm -> template bank. ``symmetry``: "auto" | "none" | "x" | "y" | "z"."""
    threads.use_budget()
    from service.vision.model.templates import build_bank

    return build_bank(mesh, symmetry=symmetry, grid=grid or {}, progress=progress)


def template_picture(bank: TemplateBank, k: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture of template k: projected mesh | extracted borderline."""
    from service.vision.model.templates import draw_template

    return draw_template(bank, k)
