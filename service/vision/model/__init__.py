"""Upload time: mesh -> symmetry axis -> rotation grid -> borderline templates -> the bank."""
