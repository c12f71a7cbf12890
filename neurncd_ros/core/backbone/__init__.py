"""Semantic embedding backbones: ESANet R34-NBt1D and the default small model."""
