"""NYU Depth v2's labelled set (``nyu_depth_v2_labeled.mat``) as Frames with NYU-13 ground truth.

The labelled set is a MATLAB v7.3 file, i.e. HDF5 (read with h5py). MATLAB
stores arrays column-major, so h5py sees every array with its axes reversed:

- ``images``: (N, 3, W, H) uint8 -> frame i is ``images[i].transpose(2, 1, 0)`` (H, W, 3) RGB;
- ``depths``: (N, W, H) float32 metres (in-painted); ``rawDepths`` the sensor's, with holes;
- ``labels``: (N, W, H) uint16, the 894-class ids (0 = unlabelled);
- ``instances``: (N, W, H) uint8 instance number within each class;
- ``names``: 894 object references to the class names; ``scenes`` and
  ``rawRgbFilenames``: one reference per frame to its scene name and the raw
  colour file it was taken from (``kitchen_0004/r-1294851097.542259-2322437371.ppm``).

The 894 classes map to NYU-40 through ``mapClass`` of ``classMapping40.mat``
(Gupta et al., the usual companion file, MATLAB v5: read with scipy), looked
for beside the labelled file unless given; NYU-40 maps to NYU-13 by
``classes.NYU40_TO_NYU13``. Images are 640x480 in the colour camera
(NYU toolbox intrinsics, preset ``nyu``). The labelled frames are single views
of many scenes: their pose is the identity; they serve backbone training and
evaluation (``neurncd train-backbone --data``), or ground truth attached to the
raw sequence they come from (:func:`raw_labels`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from .. import classes
from ..camera import Intrinsics
from ..frame import Frame
from .folder_common import PRESETS, FormatError

MATLAB_73 = b"MATLAB 7.3 MAT-file"
NUM_NYU894 = 894


def _check_v73(path: Path) -> None:
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    import h5py

    with open(path, "rb") as f:
        head = f.read(128)
    if not head.startswith(MATLAB_73) or not h5py.is_hdf5(str(path)):
        kind = head[:19].decode("latin-1", "replace") if head.startswith(b"MATLAB") else \
            "not a MATLAB file"
        raise FormatError(f"{path}: not a MATLAB v7.3 (HDF5) file ({kind!r}); NYUv2's "
                          "labelled set nyu_depth_v2_labeled.mat is v7.3")


def mapping_894_to_40(path: str | Path) -> np.ndarray:
    """``classMapping40.mat`` -> LUT (895,) uint16: 894-class id -> NYU-40 id (0 stays 0)."""
    import scipy.io

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found (the 894 -> 40 class mapping, "
                          "classMapping40.mat)")
    try:
        m = scipy.io.loadmat(str(path))
    except Exception as err:  # scipy raises several types for bad files
        raise FormatError(f"{path}: cannot read as a MATLAB file ({err})") from None
    if "mapClass" not in m:
        raise FormatError(f"{path}: no 'mapClass' variable (expected classMapping40.mat with "
                          "mapClass: 1 x 894 NYU-40 ids)")
    ids = np.asarray(m["mapClass"]).ravel()
    if ids.size != NUM_NYU894 or ids.min() < 0 or ids.max() > 40:
        raise FormatError(f"{path}: mapClass must hold 894 NYU-40 ids in 0..40, got "
                          f"{ids.size} values in {ids.min()}..{ids.max()}")
    lut = np.zeros(NUM_NYU894 + 1, dtype=np.uint16)
    lut[1:] = ids.astype(np.uint16)
    return lut


class NyuLabelled:
    """The labelled set, opened lazily: ``len``, ``frame(i)``, ``scenes``, ``raw_names``."""

    def __init__(self, mat_path: str | Path, mapping_path: str | Path | None = None) -> None:
        import h5py

        self.path = Path(mat_path)
        _check_v73(self.path)
        mapping = Path(mapping_path) if mapping_path else \
            self.path.with_name("classMapping40.mat")
        if not mapping.is_file():
            raise FormatError(f"{self.path}: the 894 -> NYU-40 class mapping is needed: put "
                              f"classMapping40.mat beside it or pass its path ({mapping} not "
                              "found)")
        self.lut40 = mapping_894_to_40(mapping)
        self.lut13 = classes.NYU40_TO_NYU13[self.lut40]
        self._h5 = h5py.File(self.path, "r")
        for key in ("images", "depths", "labels"):
            if key not in self._h5:
                raise FormatError(f"{self.path}: no '{key}' dataset; not NYUv2's labelled set "
                                  f"(has {sorted(self._h5)})")
        n, c, w, h = self._h5["images"].shape
        if c != 3 or self._h5["depths"].shape != (n, w, h) or \
                self._h5["labels"].shape != (n, w, h):
            raise FormatError(f"{self.path}: images {self._h5['images'].shape}, depths "
                              f"{self._h5['depths'].shape}, labels {self._h5['labels'].shape} "
                              "do not fit (N, 3, W, H) / (N, W, H)")
        self.size = (h, w)
        fx, fy, cx, cy = PRESETS["nyu"].intrinsics
        self.intrinsics = Intrinsics(fx, fy, cx, cy, 640, 480).scaled(w, h) \
            if (w, h) != (640, 480) else Intrinsics(fx, fy, cx, cy, 640, 480)

    def close(self) -> None:
        self._h5.close()

    def __enter__(self) -> "NyuLabelled":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return int(self._h5["images"].shape[0])

    def _strings(self, key: str) -> list[str]:
        if key not in self._h5:
            raise FormatError(f"{self.path}: no '{key}' dataset")
        refs = np.asarray(self._h5[key]).ravel()
        return ["".join(map(chr, np.asarray(self._h5[r]).ravel())) for r in refs]

    @property
    def scenes(self) -> list[str]:
        """Scene name of each frame (``kitchen_0004``)."""
        return self._strings("scenes")

    @property
    def raw_names(self) -> list[str]:
        """File name of the raw colour image each frame was taken from (base name only)."""
        return [n.replace("\\", "/").rsplit("/", 1)[-1] for n in self._strings("rawRgbFilenames")]

    def semantic(self, i: int) -> np.ndarray:
        """NYU-13 ids (H, W) uint16 of frame i."""
        lab = np.asarray(self._h5["labels"][i]).T
        if lab.size and lab.max() > NUM_NYU894:
            raise FormatError(f"{self.path}: frame {i} has label {int(lab.max())} above "
                              f"{NUM_NYU894}")
        return self.lut13[lab.astype(np.intp)].astype(np.uint16)

    def frame(self, i: int, stamp_ns: int = 0, raw_depth: bool = False) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} out of 0..{len(self) - 1}")
        rgb = np.ascontiguousarray(np.asarray(self._h5["images"][i]).transpose(2, 1, 0))
        key = "rawDepths" if raw_depth and "rawDepths" in self._h5 else "depths"
        depth = np.ascontiguousarray(np.asarray(self._h5[key][i]).T.astype(np.float32))
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        inst = None
        if "instances" in self._h5:
            inst = np.ascontiguousarray(np.asarray(self._h5["instances"][i]).T
                                        .astype(np.uint16))
        try:
            return Frame(int(stamp_ns), rgb.astype(np.uint8), depth, np.eye(4),
                         self.intrinsics, self.semantic(i), inst).validate()
        except ValueError as err:
            raise FormatError(f"{self.path}: frame {i}: {err}") from None


def read_labelled(mat_path: str | Path, mapping_path: str | Path | None = None,
                  scenes: Sequence[str] | None = None, stride: int = 1, max_frames: int = 0,
                  fps: float = 30.0, start_stamp_ns: int = 1_000_000_000,
                  raw_depth: bool = False) -> Iterator[Frame]:
    """Frames of the labelled set with NYU-13 semantic ground truth (identity poses).

    ``scenes`` keeps only frames of those scenes; stamps are made from ``fps``.
    """
    with NyuLabelled(mat_path, mapping_path) as ds:
        idx = list(range(len(ds)))
        if scenes:
            names = ds.scenes
            wanted = set(scenes)
            idx = [i for i in idx if names[i] in wanted]
            if not idx:
                raise FormatError(f"{mat_path}: no frame of scene(s) {sorted(wanted)}")
        idx = idx[::stride]
        if max_frames:
            idx = idx[:max_frames]
        for k, i in enumerate(idx):
            yield ds.frame(i, start_stamp_ns + int(round(k * 1e9 / fps)), raw_depth)


def raw_labels(mat_path: str | Path, mapping_path: str | Path | None = None
               ) -> dict[str, np.ndarray]:
    """Raw colour file name -> NYU-13 labels of the labelled frame taken from it.

    Used by ``convert`` of a raw sequence to attach the ground truth of the
    frames that belong to it (the labels are in the registered colour frame).
    """
    with NyuLabelled(mat_path, mapping_path) as ds:
        return {name: ds.semantic(i) for i, name in enumerate(ds.raw_names)}
