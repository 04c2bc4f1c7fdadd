"""Per frame: edges -> distance tensor -> coarse search -> refinement -> verdict."""
