"""RenderWorld: a camera-only driving world model built on 3D Gaussian Splatting.

Importing the package is light: it pulls in numpy only. Sub-packages are imported on use
(``renderworld.geometry``, ``renderworld.data``, ``renderworld.splat``, ...); none of them
imports Hydra, and only ``renderworld.sim`` needs Open3D.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
