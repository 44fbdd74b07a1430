"""stgc: Spacetime Gaussians with spatiotemporal KNN compaction, measured.

Layers (data flows down, nothing imports upward):
cli -> experiment -> train -> compaction | eval | codec -> model -> data | render
"""

__version__ = "0.1.0"
