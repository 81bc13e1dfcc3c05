"""Rendering of BTFs and tone mapping for display."""
