"""The part's model, made at upload: mesh -> symmetry axis -> rotation grid -> borderline templates -> the
bank; its resting poses, mirror planes and taught colours."""
