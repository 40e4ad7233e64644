"""File I/O every package shares: images (:mod:`.images`) and PLY point clouds (:mod:`.ply`).

Neutral basics: imports nothing else from edygs_ns.
"""
