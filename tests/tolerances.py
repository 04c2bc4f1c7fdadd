"""Every numeric tolerance the tests use, named, in one place (one section per area)."""

# --- conventions (frames, camera) ---
ROUND_TRIP_ATOL = 1e-9  # pure float round trips: euler <-> R <-> quat, project <-> unproject
DISTORTION_ROUND_TRIP_PX = 1e-3  # undistort(distort(uv)) against uv

# --- rendering and templates ---

# --- coarse matching ---

# --- refinement ---

# --- API ---
