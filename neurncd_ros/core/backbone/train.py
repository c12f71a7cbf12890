"""Train the default small backbone on frames with semantic ground truth.

Protocol, following NeurNCD's use of ESANet: cross-entropy over the 9 known
NYU-13 classes only; pixels of the novel classes (ceiling, picture, tv,
window) and void pixels are ignored in the loss, so the net never learns the
novel classes and its pre-softmax logits stay an honest "known-class"
embedding. Validation uses held-out frames (disjoint scenes or files).

The data is injected: :func:`train_backbone` takes train and validation
arrays (:func:`.data.frames_to_arrays` makes them from any Frames with ground
truth) and a ``source`` record of where they came from, which goes into the
training record. The synthetic scenes are one such source
(``neurncd_ros.synth.training``); bags and dataset folders are others
(``neurncd train-backbone --data``).

Known-class mIoU (percent), as reported here: over all validation pixels whose
ground truth is one of the 9 known classes, the prediction is the argmax
among the 9 channels; IoU_k = |pred=k and gt=k| / |pred=k or gt=k| counted
on those pixels only; the mean runs over the known classes present in the
validation ground truth.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .. import classes
from ..discovery.metrics import class_iou
from ..uncertainty import entropy
from . import small
from .data import IGNORE, OUTLIER, augment, check_arrays, paste_outliers, semantic_to_target

# ----------------------------------------------------------------------------- metrics
def confusion(pred: np.ndarray, target: np.ndarray, n: int = classes.NUM_KNOWN) -> np.ndarray:
    """(n, n) counts [gt, pred] over pixels whose target is a known class (< n)."""
    keep = target < n
    idx = target[keep].astype(np.int64) * n + pred[keep].astype(np.int64)
    return np.bincount(idx, minlength=n * n).reshape(n, n)


def scores_from_confusion(conf: np.ndarray) -> dict:
    """Known-class mIoU (percent, over classes present in the GT), per-class IoU, accuracy."""
    tp = np.diag(conf).astype(np.float64)
    iou, present = class_iou(conf)
    miou = float(np.nanmean(iou) * 100) if present.any() else math.nan
    acc = float(tp.sum() / max(conf.sum(), 1))
    return {"miou_known": miou, "pixel_accuracy": acc,
            "iou": {name: (None if not present[k] else round(float(iou[k]) * 100, 2))
                    for k, name in enumerate(classes.KNOWN_NAMES)}}


def evaluate(model: torch.nn.Module, data: dict[str, np.ndarray], batch: int = 8,
             progress: bool = False) -> dict:
    """Known-class mIoU etc. of ``model`` on frames ``data`` (see module doc)."""
    from tqdm import tqdm

    model.eval()
    conf = np.zeros((classes.NUM_KNOWN, classes.NUM_KNOWN), dtype=np.int64)
    n = len(data["rgb"])
    with torch.inference_mode():
        for i in tqdm(range(0, n, batch), desc="validate", disable=not progress, leave=False):
            rgb = torch.from_numpy(data["rgb"][i: i + batch]).permute(0, 3, 1, 2).float()
            depth = torch.from_numpy(np.nan_to_num(data["depth"][i: i + batch], nan=0.0,
                                                   posinf=0.0, neginf=0.0))[:, None]
            pred = model.predict_raw(rgb, depth).argmax(1).numpy()
            conf += confusion(pred, semantic_to_target(data["semantic"][i: i + batch]))
    return scores_from_confusion(conf)


def entropy_by_kind(model: torch.nn.Module, data: dict[str, np.ndarray], batch: int = 8
                    ) -> dict[str, float]:
    """Mean normalised entropy (entropy / log S) of ``model``'s softmax over the known-class
    and over the novel-class pixels of ``data``: how well its uncertainty points at what
    it never learnt (the cue discovery uses)."""
    model.eval()
    sums = {"known": [0.0, 0], "novel": [0.0, 0]}
    novel_ids = np.array(classes.NOVEL_IDS)
    with torch.inference_mode():
        for i in range(0, len(data["rgb"]), batch):
            rgb = torch.from_numpy(data["rgb"][i: i + batch]).permute(0, 3, 1, 2).float()
            depth = torch.from_numpy(np.nan_to_num(data["depth"][i: i + batch], nan=0.0,
                                                   posinf=0.0, neginf=0.0))[:, None]
            logits = model.predict_raw(rgb, depth)
            ent = (entropy(logits, dim=1) / math.log(logits.shape[1])).numpy()
            sem = data["semantic"][i: i + batch]
            for kind, sel in (("known", semantic_to_target(sem) < classes.NUM_KNOWN),
                              ("novel", np.isin(sem, novel_ids))):
                sums[kind][0] += float(ent[sel].sum())
                sums[kind][1] += int(sel.sum())
    return {k: (round(v / n, 4) if n else math.nan) for k, (v, n) in sums.items()}


# ----------------------------------------------------------------------------- training
def class_weights(targets: np.ndarray, power: float = 0.5, cap: float = 5.0) -> np.ndarray:
    """Per-class loss weights ~ frequency^-power, normalised to mean 1, capped.

    Softened inverse frequency keeps rare known classes (books, objects) from
    being swamped by wall and floor without over-predicting them.
    """
    counts = np.bincount(targets[targets != IGNORE].ravel(),
                         minlength=classes.NUM_KNOWN).astype(np.float64)
    freq = counts / max(counts.sum(), 1)
    w = np.where(freq > 0, np.maximum(freq, 1e-6) ** -power, 0.0)
    w = w / w[w > 0].mean()
    return np.minimum(w, cap).astype(np.float32)


class KnownClassESANet(torch.nn.Module):
    """ESANet R34-NBt1D trained on the known classes: its NYU-40 logits pooled
    (log-sum-exp over the channels of each class) into the 9 known NYU-13 classes.

    The loss sees only known classes, as for the default net; the network keeps
    its own head, so the result is an ordinary ESANet checkpoint
    (``{'state_dict': ...}``) that ``backbone.kind: esanet`` loads unchanged.
    """

    def __init__(self, net: torch.nn.Module, dataset: str = "nyuv2",
                 depth_mode: str = "raw") -> None:
        from .backbone import esanet_channel_to_id

        super().__init__()
        self.net, self.dataset, self.depth_mode = net, dataset, depth_mode
        ids = esanet_channel_to_id(dataset)
        if ids.size != getattr(net, "num_classes", ids.size):
            raise ValueError(f"ESANet has {net.num_classes} classes but esanet_dataset "
                             f"{dataset!r} has {ids.size}")
        for k, cid in enumerate(classes.KNOWN_IDS):
            self.register_buffer(f"group{k}", torch.from_numpy(np.flatnonzero(ids == cid)))

    def predict_raw(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        from . import esanet

        out = self.net(esanet.preprocess_rgb(rgb),
                       esanet.preprocess_depth(depth, self.dataset, self.depth_mode))
        if isinstance(out, (tuple, list)):  # training mode: side outputs follow
            out = out[0]
        return torch.stack([torch.logsumexp(out[:, getattr(self, f"group{k}")], dim=1)
                            for k in range(classes.NUM_KNOWN)], dim=1)


def _esanet_from(path: str, dataset: str, depth_mode: str) -> KnownClassESANet:
    from . import esanet

    from .backbone import esanet_channel_to_id
    net = esanet.load_esanet_checkpoint(path, num_classes=len(esanet_channel_to_id(dataset)))
    return KnownClassESANet(net, dataset, depth_mode)


def loss_terms(logits: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
               outlier_weight: float = 0.0) -> dict[str, torch.Tensor]:
    """The training objective as named terms, summed by :func:`train_step`.

    ``ce``: class-weighted cross-entropy over the known channels, void and novel
    pixels (IGNORE) and pasted outliers (OUTLIER) left out. ``oe`` (with
    ``outlier_weight`` > 0; Hendrycks et al. 2019's outlier exposure): the
    cross-entropy from the uniform distribution to the prediction on OUTLIER
    pixels, times the weight, so that unseen appearance raises the entropy. A
    new term is one more entry here; each term's mean per epoch is logged in the
    record's history.
    """
    terms = {"ce": F.cross_entropy(logits, torch.where(target == OUTLIER, IGNORE, target),
                                   weight=weights, ignore_index=IGNORE)}
    if outlier_weight > 0:
        out = target == OUTLIER
        if out.any():
            logp = F.log_softmax(logits.permute(0, 2, 3, 1)[out], dim=1)
            terms["oe"] = -outlier_weight * logp.mean()
        else:
            terms["oe"] = logits.sum() * 0.0
    return terms


def train_step(model: torch.nn.Module, opt: torch.optim.Optimizer, rgb: torch.Tensor,
               depth: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
               outlier_weight: float = 0.0, novelty_branch: bool = False) -> dict[str, float]:
    """One optimiser step on an (augmented) batch; returns the loss and its terms.
    ``novelty_branch``: the loss is on the novelty branch's logits (the rest frozen)."""
    logits = model.novelty_raw(rgb, depth) if novelty_branch else model.predict_raw(rgb, depth)
    terms = loss_terms(logits, target, weights, outlier_weight)
    loss = sum(terms.values())
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in terms.items()}}


def _init_from(model: small.SmallRGBDNet, init: str) -> dict:
    """Load ``init``'s weights into ``model``; returns what the record keeps of it."""
    if not Path(init).is_file():
        raise ValueError(f"--init {init}: no such weight file")
    prev_model = small.load_weights(init)
    if prev_model.widths != model.widths:
        raise ValueError(f"--init {init} has widths {prev_model.widths}, "
                         f"training widths {model.widths}")
    if prev_model.novelty_branch and not model.novelty_branch:
        raise ValueError(f"--init {init} has a novelty branch; train it again with "
                         "--novelty-branch or start from weights without one")
    missing, _ = model.load_state_dict(prev_model.state_dict(), strict=False)
    if any(not k.startswith("novelty_") for k in missing):
        raise ValueError(f"--init {init} lacks weights {missing[:3]}")
    if missing:  # a new novelty branch starts as a copy of the known-class head
        model.novelty_decoder.load_state_dict(model.decoder[-1].state_dict())
        model.novelty_classifier.load_state_dict(model.classifier.state_dict())
    rec_path = Path(init).with_suffix(".json")
    init_record = {"weights": str(init)}
    if rec_path.is_file():
        prev = json.loads(rec_path.read_text())
        init_record.update({k: prev.get(k) for k in (
            "command", "steps", "epochs_run", "lr", "train_seconds", "val_miou_known",
            "init", "trained_on")})
    return init_record


def train_backbone(out_path: str | Path, train: dict[str, np.ndarray],
                   val: dict[str, np.ndarray], source: dict | None = None,
                   epochs: int = 12, batch_size: int = 8, lr: float = 4e-3,
                   weight_decay: float = 1e-4, seed: int = 0,
                   max_minutes: float = 0.0, progress: bool = True,
                   crop: tuple[int, int] | None = (192, 256), init: str | None = None,
                   command: str | None = None,
                   widths: tuple[int, int, int, int] = small.DEFAULT_WIDTHS,
                   val_every: int = 0, data_seconds: float = 0.0, arch: str = "default",
                   esanet_dataset: str = "nyuv2", esanet_depth_mode: str = "raw",
                   outlier_weight: float = 0.0, outlier_prob: float = 0.5,
                   novelty_branch: bool = False) -> dict:
    """Train the default net on ``train``, save weights to ``out_path`` and the record
    next to it (``<out_path stem>.json``); returns the record.

    ``train`` / ``val``: arrays as :func:`check_arrays` wants them. ``source``
    says what they are (seeds, files, split) and is copied into the record.
    ``max_minutes`` > 0 sets the schedule length by time instead of epochs
    (the learning-rate schedule is stretched to the estimated step count).
    ``init`` continues from an earlier weight file (fine-tuning; its record, if
    beside it, is kept under "init"). ``val_every`` > 0 validates every that many
    steps and logs the score in the record's ``val_curve`` (for the record only:
    the final weights are always those of the last step, no checkpoint is
    selected on the validation data). The reported validation scores are those
    of the saved fp16 weights. ``arch="esanet"`` fine-tunes the ESANet checkpoint
    ``init`` instead (:class:`KnownClassESANet`; frame sizes multiples of 32) and
    writes an ESANet checkpoint. ``outlier_weight`` > 0 adds outlier exposure:
    with probability ``outlier_prob`` per sample a rectangle of another sample's
    known-class colour is pasted onto the destination's geometry and its prediction
    pushed towards uniform (:func:`paste_outliers`, :func:`loss_terms`).
    ``novelty_branch`` trains only a novelty branch (:mod:`.small`) added to the
    network ``init`` (which stays frozen, so its known-class argmax is unchanged),
    with the cross-entropy and the outlier exposure on the branch's logits.
    """
    from tqdm import tqdm

    if epochs < 1 or batch_size < 1:
        raise ValueError("epochs and batch_size must be >= 1")
    n = check_arrays(train, "training data")
    check_arrays(val, "validation data")
    if outlier_weight < 0 or not 0.0 <= outlier_prob <= 1.0:
        raise ValueError(f"outlier_weight must be >= 0 and outlier_prob in [0, 1], got "
                         f"{outlier_weight}, {outlier_prob}")
    if novelty_branch and (arch != "default" or not init or outlier_weight <= 0):
        raise ValueError("novelty_branch trains a branch on a trained default net: it needs "
                         "arch 'default', init=<weights> and outlier_weight > 0")
    if arch not in ("default", "esanet"):
        raise ValueError(f"arch must be 'default' or 'esanet', got {arch!r}")
    if arch == "esanet":
        if not init:
            raise ValueError("arch esanet fine-tunes a checkpoint: give init=<ESANet .pth>")
        sizes = [train["rgb"].shape[1:3], val["rgb"].shape[1:3]] + \
            ([tuple(crop)] if crop is not None else [])
        if any(h % 32 or w % 32 for h, w in sizes):
            raise ValueError(f"ESANet needs sizes divisible by 32; frames/crop are {sizes} "
                             "(e.g. --size 320 256)")
    t_start = time.time()
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)

    targets = semantic_to_target(train["semantic"])
    if not (targets != IGNORE).any():
        raise ValueError("training data has no pixel of a known class "
                         f"({', '.join(classes.KNOWN_NAMES)})")
    weights = torch.from_numpy(class_weights(targets))
    depth_all = np.nan_to_num(train["depth"], nan=0.0, posinf=0.0, neginf=0.0)
    steps_per_epoch = max(n // batch_size, 1)
    total_steps = steps_per_epoch * epochs

    if arch == "esanet":
        model = _esanet_from(init, esanet_dataset, esanet_depth_mode)
        init_record = {"weights": str(init), "esanet_dataset": esanet_dataset}
    else:
        with torch.random.fork_rng(devices=[]):  # seeded init, torch's global RNG untouched
            torch.manual_seed(seed)
            model = small.SmallRGBDNet(widths=tuple(widths), novelty_branch=novelty_branch)
        init_record = _init_from(model, init) if init else None
    if novelty_branch:
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith("novelty_"))
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=lr,
                            weight_decay=weight_decay)

    def train_mode() -> None:
        """Train mode; with the branch only the branch (the frozen net's batch-norm
        statistics must not drift)."""
        if novelty_branch:
            model.eval()
            model.novelty_decoder.train()
        else:
            model.train()
    warmup = max(min(100, total_steps // 20), 1)

    def lr_at(step: int, total: int) -> float:
        if step < warmup:
            return lr * (step + 1) / warmup
        frac = min((step - warmup) / max(total - warmup, 1), 1.0)
        return lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * frac)))

    history = []
    val_curve: list[dict] = []
    step = 0
    t_train = time.time()
    bar = tqdm(total=total_steps, desc="train backbone", disable=not progress, unit="step")
    stop = False
    for epoch in range(epochs):
        train_mode()
        order = rng.permutation(n)
        logs: list[dict[str, float]] = []
        for i in range(steps_per_epoch):
            idx = np.sort(order[i * batch_size: (i + 1) * batch_size])
            rgb = torch.from_numpy(train["rgb"][idx]).permute(0, 3, 1, 2).float()
            depth = torch.from_numpy(depth_all[idx])[:, None]
            tgt = torch.from_numpy(targets[idx]).long()
            rgb, depth, tgt = augment(rgb, depth, tgt, gen, crop=crop)
            if outlier_weight > 0:
                rgb, tgt = paste_outliers(rgb, tgt, gen, outlier_prob)
            for g in opt.param_groups:
                g["lr"] = lr_at(step, total_steps)
            logs.append(train_step(model, opt, rgb, depth, tgt, weights, outlier_weight,
                                   novelty_branch))
            if not math.isfinite(logs[-1]["loss"]):
                bar.close()
                # Nothing is saved: a diverged net's logits overflow float16 (the keyframe
                # store) and every later run ends in 'logits contain NaN or inf'.
                raise ValueError(f"training diverged at step {step + 1} (loss "
                                 f"{logs[-1]['loss']}); nothing written: lower the learning "
                                 f"rate (--lr, {lr:g} now; fine-tuning a pretrained ESANet "
                                 "wants about 1e-4)")
            step += 1
            bar.update(1)
            bar.set_postfix(epoch=epoch,
                            loss=f"{np.mean([x['loss'] for x in logs[-20:]]):.3f}")
            if max_minutes > 0 and step == 20:
                # Re-plan the schedule to fit the time budget.
                per_step = (time.time() - t_train) / step
                budget = max_minutes * 60 - (time.time() - t_start) - data_seconds
                total_steps = max(step + 1, min(total_steps, int(budget / per_step)))
                bar.total = total_steps
            if val_every > 0 and step % val_every == 0 and step < total_steps:
                score = evaluate(model, val)["miou_known"]
                val_curve.append({"step": step, "val_miou_known": round(score, 2)})
                tqdm.write(f"step {step}: validation known-class mIoU {score:.2f} %")
                train_mode()
            if step >= total_steps:
                stop = True
                break
        entry = {"epoch": epoch}
        for key in logs[0]:
            entry[key] = round(float(np.mean([x[key] for x in logs])), 4)
        if set(logs[0]) == {"loss", "ce"}:
            del entry["ce"]  # one term: the loss itself
        entry["steps"] = step
        history.append(entry)
        if stop:
            break
    bar.close()
    train_time = time.time() - t_train
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if arch == "esanet":
        torch.save({"state_dict": model.net.state_dict()}, out_path)
        shipped = _esanet_from(str(out_path), esanet_dataset, esanet_depth_mode)
    else:
        small.save_weights(model, str(out_path))
        shipped = small.load_weights(str(out_path))  # what users get: fp16 weights
    val_scores = evaluate(shipped, val, progress=progress)
    val_entropy = entropy_by_kind(shipped, val)
    source = dict(source) if source else {"trained_on": "arrays"}
    record = {
        "command": command if command is not None else " ".join(sys.argv),
        **({"arch": "SmallRGBDNet", "arch_version": small.ARCH_VERSION,
            "widths": list(model.widths),
            "parameters": small.count_parameters(model),
            "gflops_320x240": round(small.count_flops(model) / 1e9, 3)} if arch == "default"
           else {"arch": "ESANet-R34-NBt1D", "esanet_dataset": esanet_dataset,
                 "parameters": small.count_parameters(model)}),
        **{k: v for k, v in source.items() if k != "synth_config"},
        "train_frames": int(n), "train_size": [int(train["rgb"].shape[2]),
                                               int(train["rgb"].shape[1])],
        "val_frames": int(len(val["rgb"])),
        "epochs_planned": epochs, "epochs_run": len(history), "steps": step,
        "batch_size": batch_size, "lr": lr, "weight_decay": weight_decay, "seed": seed,
        "class_weights": [round(float(x), 3) for x in weights],
        "loss": "cross-entropy over 9 known classes; void and novel "
                "(ceiling, picture, tv, window) ignored" + (
                    f"; outlier exposure weight {outlier_weight}: with probability "
                    f"{outlier_prob} per sample a known-class colour rectangle of another "
                    "sample pasted on the destination's depth, pushed towards uniform"
                    if outlier_weight > 0 else "") + (
                    "; trained on a novelty branch only (the rest of --init frozen), whose "
                    "entropy scales the known-class logits" if novelty_branch else ""),
        "outlier_weight": outlier_weight, "outlier_prob": outlier_prob,
        "novelty_branch": novelty_branch,
        "augmentation": f"flip, zoom 0.8-1.35, crop {crop}, colour jitter 0.25, rgb noise",
        "val_miou_known": round(val_scores["miou_known"], 2),
        "val_pixel_accuracy": round(val_scores["pixel_accuracy"], 4),
        "val_iou": val_scores["iou"],
        "val_entropy_known": val_entropy["known"], "val_entropy_novel": val_entropy["novel"],
        "history": history, "val_curve": val_curve, "init": init_record,
        "data_seconds": round(data_seconds, 1), "train_seconds": round(train_time, 1),
        "total_seconds": round(time.time() - t_start + data_seconds, 1),
        "num_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version(),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if "synth_config" in source:
        record["synth_config"] = source["synth_config"]
    if arch == "default":
        small.save_weights(model, str(out_path),
                           extra={"val_miou_known": record["val_miou_known"]})
    record["weights_bytes"] = out_path.stat().st_size
    out_path.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    if progress:
        print(summary(record))
    return record


def summary(record: dict) -> str:
    """A few readable lines about a finished training run."""
    ious = ", ".join(f"{k} {v:.1f}" for k, v in record["val_iou"].items() if v is not None)
    return (f"trained {record['steps']} steps ({record['epochs_run']} epochs, "
            f"{record['train_frames']} frames) in {record['train_seconds'] / 60:.1f} min\n"
            f"validation {_val_text(record)}: known-class mIoU "
            f"{record['val_miou_known']:.2f} %, pixel accuracy "
            f"{record['val_pixel_accuracy'] * 100:.1f} %\nper-class IoU: {ious}\n"
            f"mean normalised entropy: known pixels {record['val_entropy_known']:.3f}, "
            f"novel pixels {record['val_entropy_novel']:.3f}")


def _val_text(record: dict) -> str:
    if "val_seeds" in record:
        return f"seeds {record['val_seeds']}"
    files = record.get("val_files")
    if files:
        return f"{record['val_frames']} frames of {', '.join(map(str, files))}"
    return f"{record['val_frames']} frames"
