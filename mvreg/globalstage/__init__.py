"""The global stage: tracks -> global solve -> robust re-weighting -> multiview refinement
-> joint point-to-plane ICP -> final checks."""
