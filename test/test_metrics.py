"""Discovery metrics against values computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from neurncd_ros.core.discovery.metrics import Evaluator, adjusted_rand_index, evaluate, purity


def _img(values):
    return np.array(values, dtype=np.uint16).reshape(1, -1)


def test_three_class_confusion_by_hand():
    # floor(5), wall(12) known, ceiling(3) novel; last pixel void.
    gt = _img([5, 5, 5, 12, 12, 3, 3, 3, 0])
    pred = _img([5, 5, 12, 12, 12, 100, 100, 5, 7])
    r = evaluate(pred, gt)
    # floor: TP 2, FP 1, FN 1 -> 1/2; wall: TP 2, FP 1 -> 2/3; ceiling (via 100): 2/3.
    assert r["iou"][5] == pytest.approx(50.0)
    assert r["iou"][12] == pytest.approx(200 / 3)
    assert r["iou"][3] == pytest.approx(200 / 3)
    assert r["iou"][1] is None  # absent from the ground truth
    assert r["miou_known"] == pytest.approx((50 + 200 / 3) / 2)
    assert r["miou_novel"] == pytest.approx(200 / 3)
    assert r["miou_all"] == pytest.approx((50 + 400 / 3) / 3)
    assert r["total_acc"] == pytest.approx(75.0)
    assert r["avg_acc"] == pytest.approx(100 * (2 / 3 + 1 + 2 / 3) / 3)
    assert r["pixels"] == 8
    assert r["novel_matching"] == {"100": 3}
    assert r["assigned_miou"] == pytest.approx(r["miou_all"])


def test_hungarian_matching_beats_greedy():
    # Overlaps: ceiling-100: 3, ceiling-101: 2, window-100: 3, window-101: 0.
    # Greedy would give 100 -> ceiling; the optimum is 100 -> window, 101 -> ceiling.
    gt = _img([3, 3, 3, 3, 3, 13, 13, 13])
    pred = _img([100, 100, 100, 101, 101, 100, 100, 100])
    r = evaluate(pred, gt)
    assert r["novel_matching"] == {"100": 13, "101": 3}
    assert r["iou"][3] == pytest.approx(40.0)   # TP 2, FN 3
    assert r["iou"][13] == pytest.approx(50.0)  # TP 3, FP 3
    assert r["miou_novel"] == pytest.approx(45.0)
    assert r["total_acc"] == pytest.approx(62.5)


def test_unmatched_cluster_and_known_id_on_novel_are_errors():
    gt = _img([3, 3, 3, 3])
    pred = _img([100, 100, 101, 12])  # 101 cannot match anything once 100 took ceiling
    r = evaluate(pred, gt)
    assert r["novel_matching"] == {"100": 3}
    assert r["iou"][3] == pytest.approx(50.0)
    assert r["iou"][12] is None
    assert r["total_acc"] == pytest.approx(50.0)


def test_accumulates_over_frames_like_one_big_image():
    rng = np.random.default_rng(0)
    gts = [rng.choice([0, 3, 5, 12, 13], size=(6, 7)).astype(np.uint16) for _ in range(3)]
    preds = [rng.choice([0, 5, 12, 100, 101], size=(6, 7)).astype(np.uint16) for _ in range(3)]
    ev = Evaluator()
    for p, g in zip(preds, gts):
        ev.update(p, g)
    joint = evaluate(np.concatenate(preds, 1), np.concatenate(gts, 1))
    assert ev.result() == joint
    assert evaluate(preds, gts) == joint


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="shape"):
        evaluate(np.zeros((2, 3), np.uint16), np.zeros((3, 2), np.uint16))
    with pytest.raises(ValueError, match="pred ids"):
        evaluate(_img([50]), _img([5]))
    with pytest.raises(ValueError, match="gt ids"):
        evaluate(_img([5]), _img([14]))
    with pytest.raises(ValueError, match="integer"):
        evaluate(np.zeros((1, 2), np.float32), np.zeros((1, 2), np.uint16))
    with pytest.raises(ValueError, match="ground-truth"):
        evaluate([_img([5])], [])


def test_adjusted_rand_and_purity_by_hand():
    truth = np.array([0, 0, 1, 1])
    assert adjusted_rand_index(truth, [5, 5, 7, 7]) == pytest.approx(1.0)
    # Contingency [[1,1],[1,1]]: index 0, expected (2*2)/6 = 2/3, max 2 -> ARI = -0.5.
    assert adjusted_rand_index(truth, [0, 1, 0, 1]) == pytest.approx(-0.5)
    assert purity(truth, [0, 0, 0, 0]) == pytest.approx(0.5)
    assert purity(truth, [0, 0, 0, 1]) == pytest.approx(0.75)
    # cluster 0 holds truth 0 weight 2 and truth 1 weight 2; cluster 1 truth 1 weight 1.
    assert purity(truth, [0, 0, 0, 1], weights=[1, 1, 2, 1]) == pytest.approx(3 / 5)


# ---------------------------------------------------------------- novel id stability

def _stability_frames():
    """Two 1x6 frames: a picture (instance 5) and a window (instance 7) beside a wall."""
    gt = np.array([[8, 8, 8, 13, 13, 12]], np.uint16)
    inst = np.array([[5, 5, 5, 7, 7, 2]], np.uint16)
    first = np.array([[100, 100, 12, 101, 101, 12]], np.uint16)
    second = np.array([[100, 101, 100, 102, 101, 100]], np.uint16)
    return gt, inst, first, second


def test_id_stability_hand_computed():
    from neurncd_ros.core.discovery.metrics import IdStability
    gt, inst, first, second = _stability_frames()
    st = IdStability()
    st.update(first, gt, inst)
    st.update(second, gt, inst)
    # picture: ids 100,100,12,100,101,100 -> 4 of 6 carry 100; novel only: 4 of 5
    # window: ids 101,101,102,101 -> 3 of 4; the wall (known class) is no novel object
    assert st.per_object() == {5: pytest.approx(4 / 6), 7: pytest.approx(3 / 4)}
    assert st.per_object(novel_only=True) == {5: pytest.approx(4 / 5), 7: pytest.approx(3 / 4)}
    r = st.result()
    assert r["novel_id_stability"] == pytest.approx((4 / 6 + 3 / 4) / 2)
    assert r["novel_id_stability_found"] == pytest.approx((4 / 5 + 3 / 4) / 2)
    assert (r["novel_objects"], r["novel_objects_found"]) == (2, 2)


def test_id_stability_perfect_and_never_found():
    from neurncd_ros.core.discovery.metrics import IdStability
    gt, inst, _, _ = _stability_frames()
    st = IdStability()
    steady = np.array([[104, 104, 104, 12, 12, 12]], np.uint16)  # window always called wall
    st.update(steady, gt, inst)
    st.update(steady, gt, inst)
    assert st.per_object() == {5: 1.0, 7: 1.0}
    assert st.per_object(novel_only=True) == {5: 1.0}
    assert st.result()["novel_objects_found"] == 1
    empty = IdStability().result()
    assert np.isnan(empty["novel_id_stability"]) and empty["novel_objects"] == 0


def test_id_stability_rejects_bad_instance():
    from neurncd_ros.core.discovery.metrics import IdStability
    gt, inst, first, _ = _stability_frames()
    with pytest.raises(ValueError, match="instance shape"):
        IdStability().update(first, gt, inst[:, :3])
    with pytest.raises(ValueError, match="instance must be an integer"):
        IdStability().update(first, gt, inst.astype(np.float32))
