"""Which synthetic scene seeds are used for what: one split for the whole project.

Every seed is a different room, so disjoint seed ranges are disjoint scenes.
Anything chosen by measurement (backbone weights, discovery and segmentation
defaults) is fitted on its own range, and every figure that claims held-out
quality is measured on ``TEST``, which nothing was ever fitted or tuned on.

- ``BACKBONE_TRAIN``: the default backbone's training scenes;
- ``BACKBONE_VAL``: its validation scenes (reported in its record, never used to
  pick weights: the last step's weights ship); also the demo's scene (1001);
- ``TUNE``: scenes on which thresholds of segmentation, clustering and labelling
  are chosen; the backbone has not seen them, so its logits there behave as on
  new scenes;
- ``TEST``: held-out scenes of the benchmarks' quality figures.
"""

from __future__ import annotations

BACKBONE_TRAIN = tuple(range(0, 180))
BACKBONE_VAL = tuple(range(1000, 1005))
TUNE = tuple(range(500, 510))
TEST = tuple(range(2000, 2010))
DEMO = 1001

_ALL = (BACKBONE_TRAIN, BACKBONE_VAL, TUNE, TEST)
assert sum(len(s) for s in _ALL) == len(set().union(*_ALL)), "seed ranges overlap"
