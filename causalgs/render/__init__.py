"""Differentiable Gaussian-splat rasterizer (Taichi kernels, one torch boundary)."""

from causalgs.render.rasterizer import Rasterizer, View, rasterize

__all__ = ["Rasterizer", "View", "rasterize"]
