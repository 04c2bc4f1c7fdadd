"""Every numeric tolerance the tests use, named, in one place (one section per area)."""

# --- conventions (frames, camera) ---
ROUND_TRIP_ATOL = 1e-9  # pure float round trips: euler <-> R <-> quat, project <-> unproject
DISTORTION_ROUND_TRIP_PX = 1e-3  # undistort(distort(uv)) against uv
# Undistorted LSD segments of a straight edge against the ideal line: their mean signed offset (an
# anti-aliased step edge is located without bias, so what is left is the lens model's doing) ...
BANDS_COVER_PX = 1.0  # detect_segments_in_bands against the whole image's LSD: a point of one's segments lies
BANDS_COVER_DEG = 10.0  # this close to a segment of the other of orientation within this ...
BANDS_COVER_SHARE = 0.95  # ... for this share of the points (pieces end differently at the bands' seam)
UNDISTORTED_EDGE_BIAS_PX = 0.25
UNDISTORTED_EDGE_NEAR_PX = 5.0  # ... over the sampled points this close to the line (not other edges)
DATASET_ANGLE_ATOL_DEG = 1e-6  # our euler / alpha-gamma against the numbers stored in gt.jsonl
RESIZE_CENTROID_PX = 0.02  # blob centroid after cv2.resize against Intrinsics.scaled's pixel-centre rule
METRIC_ATOL = 1e-6  # pose-error metrics (mm, px, deg) that are exactly 0 by construction
SYM_DISCRETISATION_DEG = 0.1  # spacing of the brute-force spin grid the closed-form axis error is checked on

# --- rendering and templates ---
RENDER_EXTENT_PX = 0.5  # silhouette width/height (from anti-aliased coverage) against the closed form
RENDER_CENTRE_PX = 0.05  # coverage centroid of a symmetric patch about the origin against (cx, cy)
RENDER_DEPTH_MM = 0.05  # z-buffer depth against the closed form (tessellated sphere, r = 100 mm)
BORDER_RADIAL_PX = 0.02  # snapped border against the closed-form silhouette (sphere, cylinder; tessellation)
BORDER_THETA_MAX_DEG = 1.0  # snapped edge orientation against the closed-form tangent (1-px polygon edges)
TRACED_RADIAL_PX = 0.15  # traced (unsnapped) supersample-4 border against the closed form
TRACED_THETA_MEAN_DEG = 1.0  # traced edge orientation against the closed-form tangent: mean ...
TRACED_THETA_MAX_DEG = 6.0  # ... and worst (the traced chain is smoothed over ~0.5 px)
BACKPROJECT_PX = 1e-3  # template pose applied to p_obj against the border point it came from
SPIN_INVARIANCE_PX = 0.5  # border of a revolved part spun about its axis against the unspun border
SYMMETRY_AXIS_DEG = 1.0  # detected symmetry axis against the true one
SYMMETRY_POINT_MM = 0.5  # distance of a known point of the true axis from the detected axis
SCANLINE_ON_CONTOUR_PX = 0.5  # the paper's scan-line border nodes against the contour-method border
SCANLINE_COVERS_CONTOUR_PX = 1.5  # contour-method border points against the scan-line border polyline

# --- coarse matching ---
DT_EXACT_ATOL = 1e-4  # DT3 against the brute-force directional chamfer minimum (exact EDT)
COARSE_AXIS_DEG = 1.5  # coarse axis direction of the revolved sprayer, distance given (target: 1 deg mean)
COARSE_XY_MM = 2.0  # coarse |tx|, |ty| at 500-600 mm (target: 1 mm mean); 1 px is ~0.5 mm here
COARSE_FREE_AXIS_DEG = 2.5  # ... with the distance estimated too (tilt and depth trade off; paper: 2.6 mean)
COARSE_FREE_DEPTH_MM = 10.0  # coarse |tz| with the distance estimated, 500-800 mm (1.5 % at 650 mm)
COARSE_OCCLUDED_AXIS_DEG = 3.0  # the same with 30 % of the object hidden
COARSE_OCCLUDED_XY_MM = 4.0
COARSE_ROT_DEG_NONSYM = 8.0  # non-symmetric part: geodesic rotation error (0.8 x the default view step)
COARSE_T_MM_NONSYM = 10.0

# --- refinement ---
REFINE_ANGLE_DEG = 0.1  # known answer: rotation (axis direction for a symmetric part) after 3 deg / 5 mm
REFINE_TRANS_MM = 0.2  # known answer: translation after 3 deg / 5 mm, distance given
REFINE_DEPTH_MM = 3.0  # |tz| when the distance is refined too (the accuracy target)
REFINE_FREE_ANGLE_DEG = 0.3  # rotation when the distance is refined too (the accuracy target)
REFINE_OCCLUDED_ANGLE_DEG = 0.3  # 30 % of the border hidden
REFINE_OCCLUDED_TRANS_MM = 0.5
REFINE_REAL_TRANS_MM = 0.2  # paper render 0001: |tx|, |ty| from gt perturbed by 1 deg / 2 mm
REFINE_REAL_AXIS_DEG = 0.3  # ... and the axis direction
REFINE_JAC_RTOL = 1e-3  # analytic Jacobian against central differences (relative to the column scale)
REFINE_JAC_ROWS = 0.97  # fraction of rows that must agree (bilinear kinks make a few rows differ)
REFINE_COMPILED_ATOL = 1e-9  # compiled residual loops against their numpy steps (float64; sums reordered)
REFINE_SAMPLE_ATOL = 1e-5  # sample_with_grad's value against chamfer.sample (float32 tensor)
REFINE_SEGMENT_DT_ATOL = 1e-4  # exact segment DT3 against brute force, px
OVERLAY_ON_BORDER_PX = 1.5  # refined-contour pixels lie this close to the rendered silhouette border

# --- API ---
API_HELD_DISTANCE_MM = 1e-6  # options.distance_mm is held: the returned t_mm z equals it
API_UNITS_CHECK_MM = 25.0  # paper/0001 at 500 mm: returned t_mm x, y within this of gt (mm, not m or px)

# --- found verdict (tests/test_found_verdict.py) ---
FOUND_POSE_T_MM = 10.0  # a found pose must be graspable: within 10 mm ...
FOUND_POSE_AXIS_DEG = 5.0  # ... and 5 deg of the truth
WARM_UP_T_MM = 1.0  # the start-up warm-up's synthetic cylinder (320 x 240, 300 mm, noise-free)
WARM_UP_AXIS_DEG = 2.0
INTERIOR_TEXTURE_MIN = 0.5  # checkerboard lines inside an empty box silhouette, per unit of perimeter
INTERIOR_PART_MAX = 0.1  # the shaded box really there: only its own creases inside

# --- the cell: robot frame and grasps (tests/test_api_cell.py, tests/test_cell.py) ---
CELL_GRASP_T_MM = 1.0  # base-frame grasp position against the known answer, rendered scene (the bar)
CELL_GRASP_ROT_DEG = 0.5  # ... and its orientation
CELL_EXACT_ATOL = 1e-9  # pure frame algebra (compositions, inverses, spins) against the closed form
CELL_SPIN_GRID_DEG = 0.05  # spacing of the brute-force spin grid the closed-form best spin is checked on

# --- resting on a plane ---
STABLE_ATOL = 1e-9  # resting rotations and face probabilities of a box (closed form)
PLANE_REST_TOL_MM = 1e-6  # a posed part built to rest on the plane touches it (pure geometry)
PLANE_FOUND_T_MM = 5.0  # instances found with a plane against the rendered copies, translation

# --- mirror twins ---
MIRROR_NORMAL_DEG = 1.0  # a detected mirror plane's normal against the true one
TWIN_OUTLINE_IOU = 0.97  # a mirror-symmetric part's twin silhouette against the pose's, seen from 20 m
TWIN_RIGHT_PX = 2.0  # the twin check's answer against the rendered truth (MSPD, px)
