"""Synthetic photometric stacks with ground truth (numpy only): shapes, materials, rigs, sensor."""

from msfnet.synth.render import RenderOptions, render_set, render_stack

__all__ = ["RenderOptions", "render_set", "render_stack"]
