"""Depth refinement of a pose: the line search ("-LS") and point-to-plane ICP."""
