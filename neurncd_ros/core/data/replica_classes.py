"""Replica's semantic classes mapped to NYU-13, so Replica ground truth needs no hand-made id map.

Replica scenes (and Semantic-NeRF's renders of them, whose ``semantic_class/``
images hold Replica class ids, 0 = void) name their classes in
``info_semantic.json`` (``{"classes": [{"id": 1, "name": "backpack"}, ...]}``),
shipped with each scene (``<scene>/habitat/info_semantic.json``, or
``semantic_info/<scene>/info_semantic.json`` beside Semantic-NeRF's sequences).
The ids are the scene file's; the names are Replica's one vocabulary, so this
module maps **names** to NYU-13 and reads the ids from the scene's file.

The mapping follows the NYU-40 -> NYU-13 table of ``core.classes``: a Replica
class goes to the NYU-40 class that NYUv2's annotators used for the same
object (door -> wall, blinds and curtain -> window, desk -> table, nightstand,
shelf, cabinets, wardrobe and counter -> furniture, rug and mat -> floor,
cushion and pillow -> objects, lamp, plants, appliances and small items ->
objects). Judgement calls, where NYU-40 has no class of its own:
``beanbag`` -> chair, ``panel`` -> wall, ``monitor`` -> objects (NYU-40 keeps
"television" alone as tv), ``major-appliance`` and ``refrigerator`` ->
furniture, ``bathtub``, ``sink``, ``toilet``, ``shower-stall`` -> objects
(NYU-40 bathtub/sink/toilet are "objects" in NYU-13), structure (``beam``,
``pillar``, ``stair``, ``handrail``, ``pipe``, ``vent``) -> objects (NYU-40
"otherstructure").

No NYU-13 counterpart (void, 0): :data:`NO_COUNTERPART` (``undefined``, Replica's
own "no class"). A class name not in :data:`REPLICA_TO_NYU13` is an error
naming it, so a new name is never silently dropped.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import classes

_GROUPS = {
    "wall": ("wall", "door", "panel"),
    "floor": ("floor", "rug", "mat"),
    "ceiling": ("ceiling",),
    "window": ("window", "blinds", "curtain"),
    "bed": ("bed",),
    "books": ("book",),
    "chair": ("chair", "stool", "beanbag"),
    "sofa": ("sofa",),
    "table": ("table", "desk"),
    "tv": ("tv-screen",),
    "picture": ("picture",),
    "furniture": ("cabinet", "base-cabinet", "wall-cabinet", "shelf", "wardrobe", "rack",
                  "tv-stand", "nightstand", "bench", "countertop", "refrigerator",
                  "major-appliance", "plant-stand"),
    "objects": ("backpack", "bag", "basket", "bathtub", "beam", "bike", "bin", "blanket",
                "bottle", "bowl", "box", "camera", "candle", "chopping-board", "clock",
                "cloth", "clothing", "coaster", "comforter", "computer-keyboard", "cooktop",
                "cup", "cushion", "desk-organizer", "desktop-computer", "exercise-ball",
                "faucet", "hair-dryer", "handbag", "handrail", "indoor-plant", "kitchen-utensil",
                "knife-block", "lamp", "laptop", "logo", "microwave", "monitor", "mouse", "pan",
                "paper-towel", "phone", "pillar", "pillow", "pipe", "plate", "pot",
                "remote-control", "scarf", "sculpture", "set-of-clothing", "shoe",
                "shower-stall", "sink", "small-appliance", "stair", "switch", "table-runner",
                "tablet", "tissue-paper", "toilet", "toothbrush", "towel", "umbrella",
                "utensil-holder", "vase", "vent", "wall-plug"),
}

NO_COUNTERPART = ("undefined",)
"""Replica classes with no NYU-13 class: their pixels become void (0)."""

REPLICA_TO_NYU13: dict[str, int] = {name: classes.CLASS_ID[group]
                                    for group, names in _GROUPS.items() for name in names}
REPLICA_TO_NYU13.update({name: classes.VOID for name in NO_COUNTERPART})


class ReplicaClassError(ValueError):
    """A Replica class file or label cannot be mapped; the text names the file."""


def find_class_info(folder: str | Path) -> Path | None:
    """The ``info_semantic.json`` of a Replica sequence folder, if one can be found.

    Looked for in the folder, ``habitat/`` beside it, its parents (up to three
    levels), and ``semantic_info/<scene>/`` in those parents, where <scene> is
    the name of any folder on the way (Semantic-NeRF: ``room_0/Sequence_1``).
    """
    folder = Path(folder).resolve()
    names = [p.name for p in [folder, *folder.parents][:4]]
    for base in [folder, *folder.parents][:4]:
        for cand in [base / "info_semantic.json", base / "habitat" / "info_semantic.json",
                     *(base / "semantic_info" / n / "info_semantic.json" for n in names)]:
            if cand.is_file():
                return cand
    return None


def read_class_info(path: str | Path) -> dict[int, str]:
    """Replica class id -> name from an ``info_semantic.json``."""
    path = Path(path)
    try:
        info = json.loads(path.read_text())
        items = info["classes"]
        out = {int(c["id"]): str(c["name"]) for c in items}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ReplicaClassError(f"{path}: not a Replica info_semantic.json with "
                                f"classes [{{id, name}}] ({type(err).__name__}: {err})") from None
    return out


def lookup_table(info_path: str | Path, mapped: set[int] = frozenset()) -> np.ndarray:
    """LUT (65536,) uint16: Replica class id of the scene -> NYU-13 id.

    Ids the file does not list map to 65535, which :func:`to_nyu13` reports. ``mapped``:
    ids the caller maps itself (a user's id_map), whose names need no entry here.
    """
    names = read_class_info(info_path)
    unknown = sorted({n for cid, n in names.items()
                      if n not in REPLICA_TO_NYU13 and cid not in mapped})
    if unknown:
        ids = sorted(cid for cid, n in names.items() if n in unknown)
        raise ReplicaClassError(f"{info_path}: Replica class name(s) {unknown} (id(s) "
                                f"{ids[:10]}) have no entry in the NYU-13 mapping "
                                "(neurncd_ros/core/data/replica_classes.py); map them with "
                                "--opt id_map=<JSON file of id -> NYU-13 id>, e.g. "
                                f"{{\"{ids[0]}\": 7}} for objects (the other ids keep the "
                                "shipped mapping)")
    lut = np.full(65536, 65535, dtype=np.uint16)
    lut[0] = classes.VOID
    for cid, name in names.items():
        if not 0 <= cid < 65535:
            raise ReplicaClassError(f"{info_path}: class id {cid} out of 0..65534")
        if name in REPLICA_TO_NYU13:
            lut[cid] = REPLICA_TO_NYU13[name]
    return lut


def to_nyu13(semantic: np.ndarray, lut: np.ndarray, where: str,
             source: str = "the scene's info_semantic.json") -> np.ndarray:
    """Map one ``semantic_class`` image; an id the mapping does not know is an error
    naming ``source`` (the class file, or the user's id_map)."""
    out = lut[semantic]
    if (out == 65535).any():
        bad = sorted(set(np.unique(semantic[out == 65535]).tolist()))[:10]
        raise ReplicaClassError(f"{where}: Replica class id(s) {bad} are not in {source}")
    return out
