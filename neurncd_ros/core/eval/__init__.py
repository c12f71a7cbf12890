"""Evaluation a researcher can publish from (issue 12): the paper's tables on bags with
ground truth, ablations and baselines, from one engine pass per bag.

``evaluate_frames`` drives the online engine (``core.engine.offline.OfflineEngine``)
over a stream once and keeps, for every labelled frame, what the rows need (the
rendered embedding and entropy, the backbone's logits, depth, pose, ground truth).
Every row is then scored with the one ``discovery.metrics.Evaluator``, on the
labelled frames that have a ground-truth image (``frames_evaluated`` of ``labelled``
per bag, as ``neurncd run`` does; a bag with none is an error naming it); each stage
after the engine pass shows a progress bar named by the stage and the bag
(``progress.py``):

- ``full`` (GS+PSSN+EP+SE+MCL): the engine's own labels, what the live graph publishes;
- ``gs_pssn_ep_mcl``: the same discovery stage with ``modulation.mode: entropy``
  (no semantic embedding in the descriptor; the backbone still names known
  clusters), re-run on the cached renderings;
- ``gs``: geometric segments clustered on geometry only (world-frame mean normal and
  height per segment, the same MCL, no names); scored by SCIM's assigned mIoU since
  its clusters carry no class names;
- ``pssn``: the backbone's argmax (known classes only);
- ``explicit``: Nakajima et al. 2019 in spirit: the per-frame backbone logits fused
  in a voxel map (running mean per voxel of back-projected points), the fused
  embedding of each frame labelled by the same discovery stage, no field;
- ``semnerf_<pct>pct``: Semantic-NeRF label propagation (``semnerf.py``): a separate
  field per label fraction with a cross-entropy head on the known classes, trained on
  ground-truth labels at that share of each keyframe's pixels with the same keyframes
  and iterations as the engine's field; scored by known-class mIoU.

``targets.py`` checks the issue's targets on the measured figures and says where and
why they fall short (eval.json ``targets``, tables.md, the summary, the report).
"""

from .evaluate import (ROWS, aggregate, evaluate_bag, evaluate_frames, markdown_tables,
                       write_eval)

__all__ = ["ROWS", "aggregate", "evaluate_bag", "evaluate_frames", "markdown_tables",
           "write_eval"]
