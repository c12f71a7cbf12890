"""Issue 12's targets checked on an evaluation's measured figures, with the shortfalls.

One implementation for ``neurncd eval`` (eval.json ``targets``, tables.md, the
printed summary), ``neurncd report`` and bench/eval.py. The targets:

- the ablation in the paper's order: full (GS+PSSN+EP+SE+MCL, mIoU all) above
  GS+PSSN+EP+MCL (mIoU all) above GS alone (SCIM's assigned mIoU: its clusters
  have no names, so its named mIoU would only see the novel matching);
- full all-class mIoU at least 10 percent above the explicit-map baseline, read
  as 10 mIoU **points** (the stricter reading for any baseline below 100 %;
  the x1.10 reading is not used anywhere);
- full known-class mIoU above Semantic-NeRF with 1 % labels.

A target whose rows were not evaluated (no ``--ablation`` / ``--baselines``) is
reported as not measured. Each missed target says by how much (once, in
:func:`lines`; ``why`` does not repeat the shortfall) and, from the figures of the
same evaluation, why.
"""

from __future__ import annotations

from typing import Any

EXPLICIT_MARGIN = 10.0
"""mIoU points the full system should be above the explicit-map baseline."""
SEMNERF_ROW = "semnerf_1pct"
FIT_CAVEAT = 0.9
"""Below this share of its own labels reproduced, a Semantic-NeRF field is short of
training, and a target met against it gets a caveat saying so."""


def _mean(agg: dict, row: str, fig: str) -> float | None:
    v = agg.get(row, {}).get(fig) or {}
    return v.get("mean")


def _gaps(agg: dict, row: str) -> str:
    """The full row's known and novel mIoU against ``row``'s, in points."""
    dk = _mean(agg, "full", "miou_known") - _mean(agg, row, "miou_known")
    dn = _mean(agg, "full", "miou_novel") - _mean(agg, row, "miou_novel")
    return f"known {dk:+.1f}, novel {dn:+.1f}"


def _span(values: list) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "?"
    return f"{min(v)}" if min(v) == max(v) else f"{min(v)}-{max(v)}"


def _target(name: str, a: float | None, b: float | None, need: float, what: str,
            missing: str) -> dict[str, Any]:
    if a is None or b is None:
        return {"target": name, "met": None, "margin": None,
                "measured": f"not measured ({missing})", "why": "", "caveat": ""}
    margin = a - b - need
    return {"target": name, "met": bool(margin > 0 if need == 0 else margin >= 0),
            "margin": float(margin), "measured": what.format(a=a, b=b, d=a - b), "why": "",
            "caveat": ""}


def check(agg: dict, bags: list[dict]) -> list[dict[str, Any]]:
    """Every target: ``target``, ``met`` (None = not measured), ``margin`` (mIoU points,
    negative = short), ``measured``, where missed ``why``, and where met against a
    baseline that did not fit its own supervision a ``caveat``."""
    full_all, full_known = _mean(agg, "full", "miou_all"), _mean(agg, "full", "miou_known")
    ep = _mean(agg, "gs_pssn_ep_mcl", "miou_all")
    gs = _mean(agg, "gs", "assigned_miou")
    ex = _mean(agg, "explicit", "miou_all")
    sn = _mean(agg, SEMNERF_ROW, "miou_known")
    it = _span([b.get("iterations") for b in bags])
    kf = _span([b.get("keyframes") for b in bags])
    out = []

    t = _target("full > GS+PSSN+EP+MCL (mIoU all)", full_all, ep, 0.0,
                "{a:.1f} vs {b:.1f} ({d:+.1f} points)", "run with --ablation")
    if t["met"] is False:
        t["why"] = (f"adding the rendered semantic embedding to the segment descriptor "
                    f"changes mIoU by ({_gaps(agg, 'gs_pssn_ep_mcl')}) points on these bags")
    out.append(t)

    t = _target("GS+PSSN+EP+MCL (mIoU all) > GS alone (assigned mIoU)", ep, gs, 0.0,
                "{a:.1f} vs {b:.1f} ({d:+.1f} points)", "run with --ablation")
    if t["met"] is False:
        t["why"] = ("geometry alone clusters these bags' segments as well as the backbone's "
                    "entropy-weighted descriptor does")
    out.append(t)

    t = _target(f"full mIoU all >= explicit map + {EXPLICIT_MARGIN:g} points", full_all, ex,
                EXPLICIT_MARGIN, "{a:.1f} vs {b:.1f} ({d:+.1f} points)", "run with --baselines")
    if t["met"] is False:
        t["why"] = (f"full minus explicit map: {_gaps(agg, 'explicit')} points. "
                    f"The explicit map averages the backbone's logits of every labelled frame "
                    f"per voxel with the bag's depth and poses, so it is already a multi-view "
                    f"fusion; the field trained {it} iterations per bag in the stream time "
                    f"(run.training_rate_hz) over {kf} keyframes and is rendered into the "
                    f"views only with mapper_node.field_views (off by default: the views are "
                    f"then the keyframes' fusion of the backbone's embeddings). Both rows "
                    f"share the backbone and the discovery stage; what the full system has "
                    f"beyond the explicit map's fusion of the same logits is its mapper "
                    f"stage: the keyframes' fusion per pixel of the view (the explicit map "
                    f"pools per voxel) and of the view's depth (mapper_node.depth_fusion; the "
                    f"explicit map segments each frame's measured depth).")
    out.append(t)

    t = _target("full mIoU known > Semantic-NeRF 1 % (mIoU known)", full_known, sn, 0.0,
                "{a:.1f} vs {b:.1f} ({d:+.1f} points)", "run with --baselines")
    infos = [b.get("semnerf", {}).get(SEMNERF_ROW, {}) for b in bags]
    fit = [i["label_fit"] for i in infos if i.get("label_fit") is not None]
    fit_s = _span([round(100 * f) for f in fit]) + " %" if fit else "?"
    sn_iterations = [i["iterations"] for i in infos if i.get("iterations") is not None]
    sn_it = _span(sn_iterations) if sn_iterations else it
    if t["met"] is False:
        lab = _span([round(i["labels_per_keyframe"]) for i in infos
                     if i.get("labels_per_keyframe") is not None])
        t["why"] = (f"with ground-truth labels at {lab} pixels per keyframe and {sn_it} "
                    f"iterations, the label-propagation field reproduces {fit_s} of its "
                    f"labels and renders the known classes better than the engine's labels "
                    f"from the backbone, which had no ground truth")
    elif t["met"] and fit and min(fit) < FIT_CAVEAT:
        factor = max((i["training_factor"] for i in infos
                      if i.get("training_factor") is not None), default=None)
        more = (f"a semnerf.training_factor above its {factor:g}" if factor is not None
                else "a larger semnerf.training_factor")
        t["caveat"] = (f"the Semantic-NeRF fields reproduce only {fit_s} of their own labels "
                       f"after {sn_it} iterations: they are short of training, so the margin "
                       f"measures the training budget more than the labels (train them longer "
                       f"with {more}, or give them longer bags)")
    out.append(t)
    return out


def lines(targets: list[dict]) -> list[str]:
    """One readable line per target (with the shortfall's reason where missed); a target
    not measured says so once, with what would measure it."""
    out = []
    for t in targets:
        if t["met"] is None:  # ``measured`` is then "not measured (run with ...)"
            out.append(f"{t['target']}: {t['measured']}")
            continue
        state = "met" if t["met"] else "SHORT"
        s = f"{t['target']}: {state}; {t['measured']}"
        if t["margin"] is not None and t["met"] is False:
            s += f", short by {-t['margin']:.1f} points"
        if t["why"]:
            s += f". Why: {t['why']}"
        if t.get("caveat"):
            s += f". Caveat: {t['caveat']}"
        out.append(s)
    return out


def markdown(targets: list[dict]) -> str:
    """tables.md's section on the targets."""
    return "\n".join(["### Issue 12 targets (mIoU points; '10 percent' read as 10 points)",
                      ""] + [f"- {x}" for x in lines(targets)]) + "\n"
