"""``neurncd report DIR``: one self-contained HTML page from an eval folder (the tables,
a picture grid in the contract's palette, the online curve, the confusion matrix).

Images are PNGs inlined as base64 so the page is one file to share."""

from __future__ import annotations

import base64
import html
import io
import json
import re
from pathlib import Path

import numpy as np

from .. import classes
from . import targets


def _png(img: np.ndarray) -> str:
    import cv2
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:
        raise ValueError("could not encode a picture")
    return base64.b64encode(buf.tobytes()).decode()


def _fig_png(fig) -> str:
    b = io.BytesIO()
    fig.savefig(b, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(b.getvalue()).decode()


def panels(res: dict, pics: dict) -> list[dict[str, str]]:
    """The grid's panels, left to right (``{"key", "title"}``): eval.json
    ``picture_panels`` as the eval wrote them; for an eval folder written before it
    was recorded, the panels every picture in pictures.npz holds."""
    if "picture_panels" in res:
        return list(res["picture_panels"])
    from .evaluate import PANELS

    frames = {k.rsplit("_", 1)[0] for k in pics}
    return [{"key": k, "title": t} for k, t in PANELS.items()
            if frames and all(f"{f}_{k}" in pics for f in frames)]


def _grid(pics: dict, parts: list[dict[str, str]]) -> list[str]:
    """One row of the ``parts`` panels (colour as is, label images in the palette) per
    kept frame."""
    frames = sorted({k.rsplit("_", 1)[0] for k in pics})
    rows = []
    for f in frames:
        tiles = [pics[f"{f}_{p['key']}"] if p["key"] == "rgb"
                 else classes.colourise(pics[f"{f}_{p['key']}"]) for p in parts]
        if tiles:
            rows.append(_png(np.concatenate(tiles, axis=1)))
    return rows


def _inline(text: str) -> str:
    """A Markdown cell as HTML: escaped, ``*x*`` (the novel classes' names) in italics."""
    return re.sub(r"\*([^*]+)\*", r"<i>\1</i>", html.escape(text))


def _md_to_html(md: str) -> str:
    out, in_table = [], False
    for line in md.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if set("".join(cells)) <= set("-"):
                continue
            tag = "th" if not in_table else "td"
            if not in_table:
                out.append("<table>")
                in_table = True
            out.append("<tr>" + "".join(f"<{tag}>{_inline(c)}</{tag}>" for c in cells)
                       + "</tr>")
            continue
        if in_table:
            out.append("</table>")
            in_table = False
        if line.startswith("### "):
            out.append(f"<h3>{html.escape(line[4:])}</h3>")
        elif line.strip():
            out.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        out.append("</table>")
    return "\n".join(out)


def render(eval_dir: str | Path, out: str | Path | None = None, notes: str = "") -> Path:
    """Write ``report.html`` in ``eval_dir`` (or ``out``); returns its path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = Path(eval_dir)
    if not (d / "eval.json").is_file():
        raise FileNotFoundError(f"{d}/eval.json not found: run neurncd eval --out {d} first")
    res = json.loads((d / "eval.json").read_text())
    md = (d / "tables.md").read_text() if (d / "tables.md").is_file() else ""
    md = md.split("### Issue 12 targets")[0]  # rendered below from eval.json itself
    pics = {}
    if (d / "pictures.npz").is_file():
        with np.load(d / "pictures.npz") as z:
            pics = {k: z[k] for k in z.files}
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>NeurNCD evaluation"
             "</title><style>body{font-family:sans-serif;max-width:1400px;margin:auto}"
             "table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #bbb;"
             "padding:2px 6px;font-size:13px}img{max-width:100%}</style></head><body>",
             "<h1>NeurNCD evaluation</h1>",
             f"<p>{len(res['bags'])} bag(s): " + html.escape(", ".join(
                 b.get("name", "") for b in res["bags"])) + "</p>"]
    checked = targets.check(res["aggregate"], res["bags"])
    parts.append("<h2>Issue 12 targets (mIoU points; '10 percent' read as 10 points)</h2>"
                 "<ul>" + "".join(f"<li>{html.escape(x)}</li>" for x in targets.lines(checked))
                 + "</ul>")
    if notes:
        parts.append(notes)
    parts.append(_md_to_html(md))
    shown = panels(res, pics)
    grid = _grid(pics, shown)
    if grid:
        parts.append("<h2>Sampled frames: " + html.escape(" | ".join(
            p["title"] for p in shown)) + "</h2>")
        parts += [f"<img src='data:image/png;base64,{g}'><br>" for g in grid]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for b in res["bags"]:
        c = b.get("curve") or []
        if c:
            k = [p["keyframes"] for p in c]
            ax.plot(k, [p["miou_known"] for p in c], "b-", alpha=0.6)
            ax.plot(k, [p["miou_novel"] for p in c], "r-", alpha=0.6)
    ax.set_xlabel("keyframes seen")
    ax.set_ylabel("mIoU so far (%)")
    ax.set_title("known (blue) and novel (red) mIoU online, one line per bag")
    parts.append("<h2>Discovery online</h2>"
                 f"<img src='data:image/png;base64,{_fig_png(fig)}'>")
    plt.close(fig)
    confs = [np.asarray(b["confusion"], np.float64) for b in res["bags"] if b.get("confusion")]
    if confs:
        conf = sum(confs)
        norm = conf / np.maximum(conf.sum(axis=1, keepdims=True), 1)
        names = [classes.class_name(i) for i in range(1, classes.NUM_CLASSES + 1)]
        fig, ax = plt.subplots(figsize=(7, 6))
        ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
        ax.set_xticks(range(len(names) + 1), names + ["none"], rotation=90, fontsize=8)
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.set_xlabel("prediction (novel clusters after Hungarian matching)")
        ax.set_ylabel("ground truth")
        for i in range(norm.shape[0]):
            for j in range(norm.shape[1]):
                if norm[i, j] >= 0.05:
                    ax.text(j, i, f"{norm[i, j]:.2f}", ha="center", va="center", fontsize=6)
        parts.append("<h2>Confusion (ours, row-normalised, all bags)</h2>"
                     f"<img src='data:image/png;base64,{_fig_png(fig)}'>")
        plt.close(fig)
    parts.append("</body></html>")
    path = Path(out) if out else d / "report.html"
    path.write_text("\n".join(parts))
    return path
