"""NYU-13 class table, the known/novel split of the paper, and the label palette.

Label ids follow the topic contract: 0 unlabelled, 1..13 the NYU-13 classes in
their standard order, novel clusters from ``NOVEL_ID_START`` upwards.
"""

from __future__ import annotations

import numpy as np

NYU13_NAMES = ("bed", "books", "ceiling", "chair", "floor", "furniture", "objects",
               "picture", "sofa", "table", "tv", "wall", "window")
"""Index i (0-based) holds the name of label id i + 1."""

NUM_CLASSES = len(NYU13_NAMES)
VOID = 0
NOVEL_ID_START = 100

CLASS_ID = {name: i + 1 for i, name in enumerate(NYU13_NAMES)}
NOVEL_NAMES = ("ceiling", "picture", "tv", "window")
NOVEL_IDS = tuple(CLASS_ID[n] for n in NOVEL_NAMES)
KNOWN_IDS = tuple(i for i in range(1, NUM_CLASSES + 1) if i not in NOVEL_IDS)
KNOWN_NAMES = tuple(NYU13_NAMES[i - 1] for i in KNOWN_IDS)
NUM_KNOWN = len(KNOWN_IDS)

# Backbone channel k (0-based) predicts NYU-13 id KNOWN_IDS[k].
CHANNEL_TO_ID = np.array(KNOWN_IDS, dtype=np.uint16)
ID_TO_CHANNEL = {cid: k for k, cid in enumerate(KNOWN_IDS)}
# The same as a lookup table over every uint16 label value: the known channel, -1 for
# void, the novel classes and anything else.
KNOWN_CHANNEL = np.full(65536, -1, dtype=np.int16)
KNOWN_CHANNEL[list(KNOWN_IDS)] = np.arange(NUM_KNOWN)

_NYU40_TO_13 = {
    "bed": [4], "books": [23], "ceiling": [22], "chair": [5], "floor": [2, 20],
    "furniture": [3, 10, 12, 15, 17, 24, 32, 39],
    "objects": [18, 19, 21, 26, 27, 28, 29, 30, 31, 33, 34, 35, 36, 37, 38, 40],
    "picture": [11], "sofa": [6], "table": [7, 14], "tv": [25], "wall": [1, 8],
    "window": [9, 13, 16],
}

NYU40_TO_NYU13 = np.zeros(41, dtype=np.uint16)
for _name, _ids in _NYU40_TO_13.items():
    NYU40_TO_NYU13[_ids] = CLASS_ID[_name]


# Fixed palette: NYU-13 colours, then a deterministic sequence for novel ids.
_KNOWN_COLOURS = np.array([
    [0, 0, 0],        # 0 unlabelled
    [0, 0, 255],      # bed
    [232, 88, 47],    # books
    [0, 217, 0],      # ceiling
    [148, 0, 240],    # chair
    [222, 241, 23],   # floor
    [255, 205, 205],  # furniture
    [0, 223, 228],    # objects
    [106, 135, 204],  # picture
    [116, 28, 41],    # sofa
    [240, 35, 235],   # table
    [0, 166, 156],    # tv
    [249, 139, 0],    # wall
    [225, 228, 194],  # window
], dtype=np.uint8)


def palette(max_id: int = 1024) -> np.ndarray:
    """RGB colour per label id (0..max_id), identical on every call and machine."""
    pal = np.zeros((max_id + 1, 3), dtype=np.uint8)
    pal[: len(_KNOWN_COLOURS)] = _KNOWN_COLOURS
    ids = np.arange(NOVEL_ID_START, max_id + 1)
    # Golden-ratio hue walk gives well separated, reproducible novel colours.
    hue = (ids - NOVEL_ID_START) * 0.618033988749895 % 1.0
    sat, val = 0.85, 0.95
    h6 = hue * 6.0
    c = val * sat
    x = c * (1 - np.abs(h6 % 2 - 1))
    m = val - c
    seg = h6.astype(int) % 6
    rgb = np.zeros((len(ids), 3))
    table = [(c, x, 0), (x, c, 0), (0, c, x), (0, x, c), (x, 0, c), (c, 0, x)]
    for s, (r, g, b) in enumerate(table):
        sel = seg == s
        rgb[sel] = np.stack([np.broadcast_to(v, sel.shape)[sel] for v in (r, g, b)], -1)
    pal[NOVEL_ID_START:] = np.round((rgb + m) * 255).astype(np.uint8)
    return pal


def colourise(labels: np.ndarray) -> np.ndarray:
    """Label image (uint16) to an RGB image with the fixed palette."""
    labels = np.asarray(labels)
    top = int(labels.max()) if labels.size else 0
    return palette(max(top, 1024))[labels]


def class_name(label_id: int) -> str:
    """Name of a label id: NYU-13 name, 'novel_<k>' or 'unlabelled'."""
    if label_id == VOID:
        return "unlabelled"
    if 1 <= label_id <= NUM_CLASSES:
        return NYU13_NAMES[label_id - 1]
    if label_id >= NOVEL_ID_START:
        return f"novel_{label_id - NOVEL_ID_START}"
    raise ValueError(f"label id {label_id} is neither NYU-13 (1..13) nor novel (>= 100)")
