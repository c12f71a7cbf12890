"""The typed records the online engine's stages pass to each other.

    Frame ──EmbeddingStage──> EmbeddingRecord ──MapperStage──> ViewRecord
          ──DiscoveryStage──> LabelsRecord

A record carries everything the next stage needs, so a stage never has to
guess or look anything up elsewhere: an embedding carries its
:class:`EmbeddingSpec` (which NYU-13 class each channel predicts, how many
feature channels follow the logits) from the backbone to the discovery, and a
view carries the colour, depth and intrinsics of the frame it was rendered
for, so a late rendering always finds its depth. Over ROS each record is a
few messages with one stamp (see ``core/topics.py``); offline they are passed
in memory.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np

from ..classes import NOVEL_ID_START, NUM_CLASSES
from ..frame import Frame


@dataclasses.dataclass(frozen=True)
class EmbeddingSpec:
    """What the channels of a semantic embedding mean.

    Channels ``0 .. S-1`` are pre-softmax logits, channel k predicting the
    NYU-13 id ``channel_to_id[k]`` (0 = a channel with no NYU-13 class);
    ``feature_channels`` more channels of the backbone's penultimate feature
    map may follow them. The spec travels with the embedding from the backbone
    (over ROS as JSON on a latched topic), so no stage infers the class of a
    channel from the channel count.
    """

    channel_to_id: tuple[int, ...]
    feature_channels: int = 0
    backbone: str = ""

    def __post_init__(self) -> None:
        ids = tuple(int(i) for i in self.channel_to_id)
        object.__setattr__(self, "channel_to_id", ids)
        if len(ids) < 2:
            raise ValueError(f"an embedding needs at least 2 logit channels, got {len(ids)}")
        if min(ids) < 0 or max(ids) > NUM_CLASSES:
            raise ValueError(f"channel_to_id must hold NYU-13 ids 0..{NUM_CLASSES}, got "
                             f"{list(ids)}")
        if not any(ids):
            raise ValueError("no embedding channel predicts an NYU-13 class")
        if int(self.feature_channels) < 0:
            raise ValueError(f"feature_channels must be >= 0, got {self.feature_channels}")
        object.__setattr__(self, "feature_channels", int(self.feature_channels))

    @property
    def logit_channels(self) -> int:
        """S: the number of class-score channels."""
        return len(self.channel_to_id)

    @property
    def channels(self) -> int:
        """All channels of the embedding image: logits then features."""
        return self.logit_channels + self.feature_channels

    def ids(self) -> np.ndarray:
        """channel_to_id as a uint16 array (for indexing by argmax)."""
        return np.asarray(self.channel_to_id, dtype=np.uint16)

    def check(self, embedding: np.ndarray, what: str = "embedding") -> np.ndarray:
        """Validate an (H, W, channels) floating embedding against this spec."""
        emb = np.asarray(embedding)
        if emb.ndim != 3 or emb.shape[2] != self.channels:
            raise ValueError(f"{what} has shape {emb.shape}, the spec says (H, W, "
                             f"{self.channels}) ({self.logit_channels} logits + "
                             f"{self.feature_channels} features)")
        if not np.issubdtype(emb.dtype, np.floating):
            raise ValueError(f"{what} must be floating point, got {emb.dtype}")
        return emb

    def to_json(self) -> str:
        return json.dumps({"channel_to_id": list(self.channel_to_id),
                           "feature_channels": self.feature_channels,
                           "backbone": self.backbone}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "EmbeddingSpec":
        """Parse :meth:`to_json` output; ValueError naming what is wrong."""
        try:
            d = json.loads(text)
        except (TypeError, json.JSONDecodeError) as err:
            raise ValueError(f"embedding spec is not JSON: {err}") from None
        if not isinstance(d, dict) or not isinstance(d.get("channel_to_id"), list):
            raise ValueError(f"embedding spec needs a 'channel_to_id' list, got {text[:200]!r}")
        try:
            return cls(tuple(int(i) for i in d["channel_to_id"]),
                       int(d.get("feature_channels", 0)), str(d.get("backbone", "")))
        except (TypeError, ValueError) as err:
            raise ValueError(f"bad embedding spec {text[:200]!r}: {err}") from None


@dataclasses.dataclass
class EmbeddingRecord:
    """The backbone's embedding of one frame.

    ``embedding`` (h, w, C) float32 or float16, possibly coarser than the frame
    (same aspect); the first ``spec.logit_channels`` channels are logits.
    """

    stamp_ns: int
    embedding: np.ndarray
    spec: EmbeddingSpec

    @property
    def logits(self) -> np.ndarray:
        return self.embedding[..., : self.spec.logit_channels]


@dataclasses.dataclass
class ViewRecord:
    """A frame rendered by the Embedding-NeRF (or, where the field has not learnt it yet,
    completed from the backbone), with the frame it belongs to.

    - ``frame``: colour, depth, pose and intrinsics of the rendered view (full size);
    - ``embedding``: (h, w, C) rendered embedding, ``entropy``: (h, w) entropy of
      the softmax of its logit channels (plus ``mapper_node.disagreement_weight``
      times the fused views' disagreement, when set), at the render resolution
      (``render_scale``);
    - ``field_share``: share of pixels taken from the field rather than the backbone;
    - ``keyframe``: the frame was admitted as a keyframe;
    - ``iterations``: field training iterations when it was rendered;
    - ``depth``: the view's depth as discovery gets it, full size: the measured depth
      averaged with the keyframes' (``mapper_node.depth_fusion``); None = the frame's
      measured depth (:attr:`view_depth` gives either).
    """

    frame: Frame
    embedding: np.ndarray
    entropy: np.ndarray
    spec: EmbeddingSpec
    keyframe: bool = False
    field_share: float = 1.0
    iterations: int = 0
    depth: np.ndarray | None = None

    @property
    def stamp_ns(self) -> int:
        return self.frame.stamp_ns

    @property
    def view_depth(self) -> np.ndarray:
        """The depth discovery segments: fused if the mapper fused it, else measured."""
        return self.frame.depth if self.depth is None else self.depth


@dataclasses.dataclass
class LabelsRecord:
    """The published result for one frame: (H, W) uint16 labels at the depth frame's size
    (0 unlabelled, 1..13 NYU-13, novel ids from 100) and the class table."""

    stamp_ns: int
    labels: np.ndarray
    classes: dict[int, dict[str, Any]]
    keyframe: bool = False

    def __post_init__(self) -> None:
        lab = np.asarray(self.labels)
        if lab.ndim != 2 or lab.dtype != np.uint16:
            raise ValueError(f"labels must be (H, W) uint16, got {lab.shape} {lab.dtype}")
        ids = np.unique(lab)
        bad = ids[(ids > NUM_CLASSES) & (ids < NOVEL_ID_START)]
        if bad.size:
            raise ValueError(f"label ids {bad.tolist()} are neither NYU-13 nor novel")
