"""Embedding-NeRF: fields, samplers, renderer, losses, keyframe buffer and mapper."""
