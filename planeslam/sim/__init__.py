"""Synthetic RGB-D scenes with exact truth: scene geometry (`scenes`) and the renderer
with a Kinect-like noise model (`render`)."""
