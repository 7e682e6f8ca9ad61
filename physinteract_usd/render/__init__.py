"""Differentiable Gaussian-splat renderer in Warp, SH colours, deformation by the simulator, losses."""

from .function import RasterizeGaussians, cov6_from_matrix, matrix_from_cov6, project, render
from .rasterizer import RasterSettings
from .sh import eval_sh, sh_basis, sh_to_color

__all__ = ["RasterSettings", "RasterizeGaussians", "render", "project", "cov6_from_matrix",
           "matrix_from_cov6", "eval_sh", "sh_basis", "sh_to_color"]
