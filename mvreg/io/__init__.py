"""Input and output: scan loaders, pose files, problem files, atomic writers."""
