"""Slow reference code the fast paths are checked against (the paper's equations, pose errors); the
hot path imports nothing from here."""
