"""The learned scene: canonical (t = 0) Gaussians, their training, and the dynamics that move them."""
