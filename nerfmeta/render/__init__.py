"""Rendering maths: pure functions over tensors (rays, sampling, volume compositing)."""
