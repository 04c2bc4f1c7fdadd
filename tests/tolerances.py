"""Every numeric tolerance the tests use, named, in one place (one section per area)."""

# --- conventions (frames, camera) ---
ROUND_TRIP_ATOL = 1e-9  # pure float round trips: euler <-> R <-> quat, project <-> unproject
DISTORTION_ROUND_TRIP_PX = 1e-3  # undistort(distort(uv)) against uv
DATASET_ANGLE_ATOL_DEG = 1e-6  # our euler / alpha-gamma against the numbers stored in gt.jsonl
RESIZE_CENTROID_PX = 0.02  # blob centroid after cv2.resize against Intrinsics.scaled's pixel-centre rule

# --- rendering and templates ---

# --- coarse matching ---

# --- refinement ---

# --- API ---
