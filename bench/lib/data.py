"""The data sets (``../shared/data/<set>/``: ``gt.jsonl``, ``meta.json``, ``images/``, ``models/``), their
template banks (built once, cached in ``bench/out/banks``) and the errors of a pose against a gt line."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from service.vision.bank import BANK_FORMAT_VERSION, TemplateBank
from service.vision.geometry.frames import Pose
from service.vision.reference import metrics

ROOT = Path(__file__).resolve().parents[2]
DATA_DIR = Path(os.environ.get("POSE_DATA_DIR", ROOT.parent / "shared" / "data"))
OUT_DIR = ROOT / "bench" / "out"

MIN_VISIBLE = 0.5  # targets at least half visible are evaluated
RIGHT_PX = 20.0  # MSPD at 640 px width: a pose under this is right (BOP's loosest threshold)
FINE_PX = 5.0
# Linemod-Occluded's object numbers, as the README names them
PART_NAMES = {"lmo_01": "ape", "lmo_05": "can", "lmo_06": "cat", "lmo_08": "driller", "lmo_09": "duck",
              "lmo_10": "eggbox", "lmo_11": "glue", "lmo_12": "holepuncher"}
MAX_METRIC_POINTS = 1000  # model vertices for MSPD / MSSD (hull + seeded sample); ADD(-S) use all
SYMMETRY_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def set_dir_of(name: str, data: Path | None = None) -> Path:
    """A set's folder: ``name`` itself if it is one (e.g. a ``bench/synth_scenes.py`` output), else the
    set of that name under ``data`` (default ``DATA_DIR``)."""
    p = Path(name)
    return p if p.is_dir() else (data or DATA_DIR) / name


def read_colour(path: Path) -> np.ndarray:
    """The image file as stored (colour BGR, grey, 16-bit): what a cell posts."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f"cannot read {path}")
    return img


def read_grey(path: Path) -> np.ndarray:
    """(H, W) uint8/uint16 grey image, read unchanged and converted from colour if needed."""
    img = read_colour(path)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return img


def read_gt(set_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (set_dir / "gt.jsonl").read_text().splitlines() if line.strip()]


def read_meta(set_dir: Path) -> dict:
    p = set_dir / "meta.json"
    return json.loads(p.read_text()) if p.exists() else {}


def symmetry_axis(g: dict) -> np.ndarray | None:
    """The ground truth's symmetry axis (object frame) from its "symmetry" field; never from the bank."""
    s = g.get("symmetry", "none")
    return None if s in (None, "none") else np.asarray(SYMMETRY_AXES[s], float)


@dataclass
class ModelInfo:
    name: str
    mesh_path: Path
    pts_obj: np.ndarray  # (N, 3) float64 mm: <= MAX_METRIC_POINTS vertices for MSPD / MSSD
    vertices_obj: np.ndarray  # (V, 3) float64 mm: every vertex, for ADD / ADD-S (closest-point density)
    diameter_mm: float


def load_model_info(set_dir: Path, model: str, meta: dict, cache: dict) -> ModelInfo:
    import trimesh

    mesh_path = set_dir / "models" / f"{model}.stl"
    key = str(mesh_path)
    if key in cache:
        return cache[key]
    mesh = trimesh.load(mesh_path, force="mesh")
    v = v_all = np.unique(np.asarray(mesh.vertices, float), axis=0)
    if len(v) > MAX_METRIC_POINTS:  # half from the convex hull (the extremes), half from the rest
        from scipy.spatial import ConvexHull

        rng = np.random.default_rng(0)
        hull = ConvexHull(v).vertices
        if len(hull) > MAX_METRIC_POINTS // 2:
            hull = rng.choice(hull, size=MAX_METRIC_POINTS // 2, replace=False)
        rest = np.setdiff1d(np.arange(len(v)), hull)
        more = rng.choice(rest, size=min(MAX_METRIC_POINTS - len(hull), len(rest)), replace=False)
        v = v[np.sort(np.concatenate([hull, more]))]
    d = meta.get("models", {}).get(model, {}).get("diameter_mm")
    info = ModelInfo(model, mesh_path, v, v_all, float(d) if d else metrics.diameter_mm(mesh.vertices))
    cache[key] = info
    return info


VISION = ROOT / "service" / "vision"
# The code that builds a bank: the build and geometry rooms, and the bank's own format.
BANK_SOURCES = (*sorted((VISION / "model").glob("*.py")), *sorted((VISION / "geometry").glob("*.py")),
                VISION / "bank.py")


def bank_path(model: str, mesh_path: Path, grid: dict | None) -> Path:
    h = hashlib.sha1()
    h.update(json.dumps(grid or {}, sort_keys=True).encode())
    h.update(hashlib.sha1(mesh_path.read_bytes()).digest())
    h.update(str(BANK_FORMAT_VERSION).encode())
    for src in BANK_SOURCES:  # a change invalidates the cache
        h.update(src.read_bytes())
    return OUT_DIR / "banks" / f"{model}-{h.hexdigest()[:12]}.npz"


_BANKS: dict[tuple[str, str, str], TemplateBank] = {}


def load_bank(model: str, mesh_path: Path, grid: dict | None, *, rebuild: bool = False) -> TemplateBank:
    """Build the template bank once per (model, grid) and cache it as .npz."""
    import trimesh

    from service.vision.pipeline import build_templates

    key = (model, hashlib.sha1(mesh_path.read_bytes()).hexdigest(), json.dumps(grid or {}, sort_keys=True))
    if key in _BANKS:  # one bank per model for the whole invocation, even if the code changes meanwhile
        return _BANKS[key]
    path = bank_path(model, mesh_path, grid)
    if path.exists() and not rebuild:
        with np.load(path) as a:
            _BANKS[key] = TemplateBank.from_arrays(dict(a))
        return _BANKS[key]
    t0 = time.perf_counter()
    bank = build_templates(trimesh.load(mesh_path, force="mesh"), symmetry="auto", grid=grid)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **bank.to_arrays())
    _BANKS[key] = bank
    print(f"built bank {path.name}: {bank.n_templates} templates in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    return bank


def gt_bank(set_dir: Path, model: str) -> TemplateBank:
    """``load_bank`` of a data set's model (``models/<model>.stl``), default grid."""
    return load_bank(model, set_dir / "models" / f"{model}.stl", None)


def stage_errors(pose: Pose | None, g: dict, info: ModelInfo, K: np.ndarray, width: int) -> dict:
    """Every error of one estimated pose against the ground truth; NaN-filled when there is none."""
    keys = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "rz_deg", "re_deg", "te_mm", "mspd_px", "mspd640_px",
            "mssd_mm", "adds_mm", "add_mm")
    if pose is None:
        return {k: float("nan") for k in keys} | {"has_pose": False}
    R_g, t_g = np.asarray(g["R"], float), np.asarray(g["t_mm"], float)
    R_e, t_e = np.asarray(pose.R, float), np.asarray(pose.t_mm, float)
    axis = symmetry_axis(g)
    e = metrics.paper_errors(R_e, t_e, R_g, t_g, axis)
    syms = metrics.pose_symmetries(R_e, R_g, axis)
    mspd = metrics.mspd_px(R_e, t_e, R_g, t_g, K, info.pts_obj, syms)
    return {
        "tx_mm": e["tx_mm"], "ty_mm": e["ty_mm"], "tz_mm": e["tz_mm"], "rx_deg": e["rx_deg"],
        "rz_deg": e["rz_deg"], "re_deg": e["re_deg"], "te_mm": metrics.te_mm(t_e, t_g),
        "mspd_px": mspd, "mspd640_px": mspd * 640.0 / width,
        "mssd_mm": metrics.mssd_mm(R_e, t_e, R_g, t_g, info.pts_obj, syms),
        "adds_mm": metrics.add_s_mm(R_e, t_e, R_g, t_g, info.vertices_obj),
        "add_mm": metrics.add_mm(R_e, t_e, R_g, t_g, info.vertices_obj),
        "has_pose": True,
    }


def mspd640(pose: Pose, g: dict, info: ModelInfo) -> float:
    """MSPD of ``pose`` against the gt line, in pixels at 640 px width (BOP)."""
    return stage_errors(pose, g, info, np.asarray(g["K"], float), int(g["width"]))["mspd640_px"]
