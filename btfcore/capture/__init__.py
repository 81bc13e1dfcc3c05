"""Capture: raw exposure brackets to rectified linear textures (thesis §1.1.3, paper 2-3)."""
