"""Label fusion: the voxel map keeps a surface's novel id across frames and poses."""

from __future__ import annotations

import numpy as np
import pytest

from neurncd_ros.core.camera import Intrinsics, look_at
from neurncd_ros.core.classes import CHANNEL_TO_ID, CLASS_ID, NOVEL_ID_START
from neurncd_ros.core.discovery.fusion import LabelFusionConfig, LabelFusion

H, W = 120, 160  # 1.25 cm per pixel on the plane, finer than a voxel
INTR = Intrinsics.from_hfov(W, H, 90.0)
WALL, CHAIR, TABLE = CLASS_ID["wall"], CLASS_ID["chair"], CLASS_ID["table"]
NOVEL = NOVEL_ID_START + 2


def _wall_pose(x: float) -> np.ndarray:
    """A camera at (x, 0, 0) looking along +y at the plane y = 1 (world z up)."""
    return look_at(np.array([x, 0.0, 0.0]), np.array([x, 1.0, 0.0]))


def _plane_depth(pose: np.ndarray, plane_y: float = 1.0) -> np.ndarray:
    """Depth of the plane y = ``plane_y`` seen from ``pose`` (z-depth along the optical
    axis)."""
    v, u = np.mgrid[0:H, 0:W]
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones((H, W))], -1)
    dw = d @ pose[:3, :3].T
    return ((plane_y - pose[1, 3]) / dw[..., 1]).astype(np.float32)


def _world_x(pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World x of every pixel (the plane's horizontal coordinate)."""
    v, u = np.mgrid[0:H, 0:W]
    cam = np.stack([(u - INTR.cx) / INTR.fx * depth, (v - INTR.cy) / INTR.fy * depth, depth], -1)
    return (cam @ pose[:3, :3].T + pose[:3, 3])[..., 0]


def _labels_with_picture(pose, depth, lo=-0.3, hi=0.3):
    """Wall everywhere, a novel "picture" where the plane's world x is in [lo, hi]."""
    x = _world_x(pose, depth)
    return np.where((x > lo) & (x < hi), NOVEL, WALL).astype(np.uint16), (x > lo) & (x < hi)


def test_a_surface_keeps_its_novel_id_when_one_frame_calls_it_wall():
    fus = LabelFusion(LabelFusionConfig(voxel_size=0.03, decay=0.9))
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    lab, pic = _labels_with_picture(pose, depth)
    for _ in range(5):
        out = fus.update(lab, depth, INTR, pose, {NOVEL})
    assert np.array_equal(out, lab), "a steady labelling passes through unchanged"
    wall_only = np.full((H, W), WALL, np.uint16)
    out = fus.update(wall_only, depth, INTR, pose, {NOVEL})
    assert (out[pic] == NOVEL).mean() > 0.95 and (out[~pic] == WALL).all()
    # A lasting change wins after a few frames.
    for _ in range(20):
        out = fus.update(wall_only, depth, INTR, pose, {NOVEL})
    assert (out == WALL).all()


def test_the_map_is_in_world_coordinates():
    """Seen from a camera moved 0.4 m sideways, the picture keeps its id where it lies
    in the world, i.e. at other pixels than in the first view."""
    fus = LabelFusion(LabelFusionConfig(voxel_size=0.03, decay=0.9))
    a = _wall_pose(0.0)
    da = _plane_depth(a)
    lab_a, _ = _labels_with_picture(a, da)
    for _ in range(4):
        fus.update(lab_a, da, INTR, a, {NOVEL})
    b = _wall_pose(0.4)
    db = _plane_depth(b)
    _, pic_b = _labels_with_picture(b, db)
    out = fus.update(np.full((H, W), WALL, np.uint16), db, INTR, b, {NOVEL})
    assert pic_b.sum() > 50
    assert (out[pic_b] == NOVEL).mean() > 0.9
    assert (out[~pic_b] == WALL).mean() > 0.97
    _, pic_a_in_b = _labels_with_picture(a, da)
    assert not np.array_equal(pic_a_in_b, pic_b), "the object moved in the image"


def test_known_changes_are_left_to_the_frame_and_retired_ids_lose_their_votes():
    fus = LabelFusion(LabelFusionConfig(voxel_size=0.03, decay=0.9))
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    lab, pic = _labels_with_picture(pose, depth)
    chair = np.where(pic, NOVEL, CHAIR).astype(np.uint16)
    for _ in range(5):
        fus.update(chair, depth, INTR, pose, {NOVEL})
    table = np.where(pic, NOVEL, TABLE).astype(np.uint16)
    out = fus.update(table, depth, INTR, pose, {NOVEL})
    assert (out[~pic] == TABLE).all(), "known-to-known: the frame decides (novel_only)"
    # Discovery retired the id: the map no longer brings it back.
    out = fus.update(np.full((H, W), TABLE, np.uint16), depth, INTR, pose, set())
    assert (out == TABLE).all()
    # Without novel_only the map holds a known label too.
    all_cls = LabelFusion(LabelFusionConfig(voxel_size=0.03, decay=0.9, novel_only=False))
    for _ in range(5):
        all_cls.update(chair, depth, INTR, pose, {NOVEL})
    out = all_cls.update(table, depth, INTR, pose, {NOVEL})
    assert (out[~pic] == CHAIR).all()


def test_pixels_without_depth_or_label_and_the_voxel_bound():
    fus = LabelFusion(LabelFusionConfig(voxel_size=0.03, decay=0.9, max_voxels=1000))
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    lab, pic = _labels_with_picture(pose, depth)
    fus.update(lab, depth, INTR, pose, {NOVEL})
    assert len(fus) == 1000, "bounded: the plane has more voxels than that"
    holes = depth.copy()
    holes[:, :10] = np.nan
    holes[:, 10:20] = 0.0
    unlabelled = lab.copy()
    unlabelled[pic] = 0
    out = fus.update(unlabelled, holes, INTR, pose, {NOVEL})
    assert (out[:, :20] == unlabelled[:, :20]).all(), "no depth: the frame's label stays"
    with pytest.raises(ValueError, match="labels are"):
        fus.update(lab[:10], depth, INTR, pose)
    with pytest.raises(ValueError, match="pose"):
        fus.update(lab, depth, INTR, np.eye(3))


def _picture_view(x: float, rng, picture: bool = True):
    """The plane seen from (x, 0, 0): confident wall logits, and a 0.6 x 0.4 m picture
    at the world origin with the uncertain channel mix of an unseen class."""
    pose = _wall_pose(x)
    depth = _plane_depth(pose)
    v = np.mgrid[0:H, 0:W][0]
    pic = (np.abs(_world_x(pose, depth)) < 0.3) & (np.abs((v - INTR.cy) / INTR.fy * depth) < 0.2)
    emb = rng.normal(0, 0.3, (H, W, len(CHANNEL_TO_ID))).astype(np.float32)
    emb[..., list(CHANNEL_TO_ID).index(WALL)] += 5.0
    if picture:
        emb[pic] = rng.normal(0, 0.3, (int(pic.sum()), len(CHANNEL_TO_ID)))
        emb[pic, 0] += 1.2
        emb[pic, 1] += 1.0
    return pose, depth, emb, pic


def test_discoverer_fuses_with_a_pose_and_labels_alone_without():
    """The Discoverer end to end: the picture is found as novel; a later frame whose
    embedding calls it wall keeps its id where the map saw it (with the pose), and is
    all wall without the pose."""
    from neurncd_ros.core.discovery.labeller import Discoverer, DiscoveryConfig
    from neurncd_ros.core.uncertainty import entropy

    def run(with_pose: bool):
        rng = np.random.default_rng(0)
        d = Discoverer(DiscoveryConfig(), CHANNEL_TO_ID)
        for i in range(5):
            pose, depth, emb, pic = _picture_view(0.05 * i, rng)
            lab = d.process(depth, INTR, emb, entropy(emb), i, None,
                            pose=pose if with_pose else None)
            assert (lab[pic] >= NOVEL_ID_START).mean() > 0.95
        pose, depth, emb, pic = _picture_view(0.3, rng, picture=False)
        out = d.process(depth, INTR, emb, entropy(emb), 5, None,
                        pose=pose if with_pose else None)
        return lab, out, pic, d

    lab, out, pic, d = run(True)
    novel_id = int(np.bincount(lab[lab >= NOVEL_ID_START]).argmax())
    assert (out[pic] == novel_id).mean() > 0.9
    assert (out[~pic] == WALL).mean() > 0.97
    assert d.classes()[novel_id] == {"name": d.classes()[novel_id]["name"], "kind": "novel",
                                     "pixels": int((out == novel_id).sum())}
    _, alone, _, _ = run(False)
    assert (alone == WALL).all()


def test_a_bad_pose_is_refused_before_discovery_changes_state():
    from neurncd_ros.core.discovery.labeller import Discoverer, DiscoveryConfig
    from neurncd_ros.core.uncertainty import entropy

    rng = np.random.default_rng(0)
    d = Discoverer(DiscoveryConfig(), CHANNEL_TO_ID)
    pose, depth, emb, _ = _picture_view(0.0, rng)
    d.process(depth, INTR, emb, entropy(emb), 0, None, pose=pose)
    before = (d.memory_len, len(d.fusion), d.classes())
    bad = pose.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="view pose"):
        d.process(depth, INTR, emb, entropy(emb), 1, None, pose=bad)
    assert (d.memory_len, len(d.fusion), d.classes()) == before



def test_a_second_novel_id_on_a_surface_the_map_gives_another_takes_that_id():
    """One wide picture: a first view calls it NOVEL, a view from further right calls it
    NOVEL + 1 (Markov clustering split it); the part only the second view sees is
    published as NOVEL too, and so are later frames, while discovery keeps both ids.
    Without aliases the new part keeps NOVEL + 1."""
    other = NOVEL + 1

    def views(cfg: LabelFusionConfig):
        fus = LabelFusion(cfg)
        a = _wall_pose(-0.4)
        da = _plane_depth(a)
        lab_a, _ = _labels_with_picture(a, da, -0.9, 0.9)
        for _ in range(3):
            fus.update(lab_a, da, INTR, a, {NOVEL})
        b = _wall_pose(0.6)
        db = _plane_depth(b)
        lab_b, pic_b = _labels_with_picture(b, db, -0.9, 0.9)
        lab_b[pic_b] = other
        new_part = pic_b & (_world_x(b, db) > 0.6)  # the first view never saw it
        assert new_part.sum() > 100
        return fus, [fus.update(lab_b, db, INTR, b, {NOVEL, other}) for _ in range(2)], \
            pic_b, new_part, (lab_b, db, b)

    fus, outs, pic_b, new_part, (lab_b, db, b) = views(LabelFusionConfig(alias_share=0.4))
    for out in outs:
        assert (out[pic_b] == NOVEL).all() and (out[~pic_b] == WALL).all()
    assert fus.aliases == {other: NOVEL}
    # An aliased id is never published: not where the frame has no depth either (its
    # label is the frame's own there), so every id shown is one the class table lists.
    holes = db.copy()
    holes[:, ::7] = 0.0
    out = fus.update(lab_b, holes, INTR, b, {NOVEL, other})
    assert other not in np.unique(out) and (out[pic_b] == NOVEL).all()
    # Discovery retires NOVEL but keeps NOVEL + 1: the id it is published as stays.
    out = fus.update(lab_b, db, INTR, b, {other})
    assert (out[pic_b] == NOVEL).all()
    # Discovery retires NOVEL + 1: the alias goes with it.
    fus.update(np.full((H, W), WALL, np.uint16), db, INTR, b, {NOVEL})
    assert fus.aliases == {}

    # Two ids side by side in one frame are two objects to discovery: the right one lies
    # mostly (2/3) on surface the map gives the left one, and still keeps its id.
    # (touch_share off: this is the map's rule alone; the touching rule is tested below.)
    fus = LabelFusion(LabelFusionConfig(alias_share=0.4, touch_share=0.0))
    a = _wall_pose(-0.4)
    da = _plane_depth(a)
    lab_a, _ = _labels_with_picture(a, da, -0.9, 0.9)
    for _ in range(3):
        fus.update(lab_a, da, INTR, a, {NOVEL})
    right = pic_b & (_world_x(b, db) > 0.0)
    both = np.where(right, other, lab_b).astype(np.uint16)
    both[pic_b & ~right] = NOVEL
    out = fus.update(both, db, INTR, b, {NOVEL, other})
    assert fus.aliases == {} and (out[new_part] == other).all()

    # The share rule alone (touch_mapped off: the new id touches the old one in the fused
    # labels, and that rule would join them; tested below).
    _, outs, pic_b, new_part, _ = views(LabelFusionConfig(alias_share=0.0,
                                                          touch_mapped=False))
    assert (outs[-1][new_part] == other).all()
    # Where a novel id only touches another's surface (under the share), it keeps its id.
    _, outs, pic_b, new_part, _ = views(LabelFusionConfig(alias_share=0.95,
                                                          touch_mapped=False))
    assert (outs[-1][new_part] == other).all()
    _, outs, pic_b, new_part, _ = views(LabelFusionConfig(alias_share=0.95))
    assert (outs[-1][pic_b] == NOVEL).all()  # touch_mapped joins them


@pytest.mark.parametrize("coarse", [0.15, 0.0])
def test_fresh_voxels_take_their_neighbourhoods_novel_label(coarse):
    """The same picture measured 5 cm closer (depth noise, a new viewpoint) falls on new
    3 cm voxels; the frame calls it wall. With the coarse map its first observations keep
    the picture's id; then the fine voxels' own votes decide. Without it, wall at once."""
    fus = LabelFusion(LabelFusionConfig(voxel_size=0.03, coarse_voxel_size=coarse,
                                        fresh_observations=1))
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    lab, pic = _labels_with_picture(pose, depth)
    for _ in range(5):
        fus.update(lab, depth, INTR, pose, {NOVEL})
    near = _plane_depth(pose, 0.95)
    _, pic_near = _labels_with_picture(pose, near)
    wall_only = np.full((H, W), WALL, np.uint16)
    for frame in range(3):
        out = fus.update(wall_only, near, INTR, pose, {NOVEL})
        if coarse and frame < 2:  # observed at most fresh_observations times before
            assert (out[pic_near] == NOVEL).mean() > 0.9
            # Wall pixels away from the picture stay wall (its coarse voxels' edge aside).
            x = _world_x(pose, near)
            assert (out[np.abs(x) > 0.3 + coarse] == WALL).all()
        else:
            assert (out == WALL).all()
    # Known labels never come from the coarse map: a fresh surface the frame calls
    # chair stays chair although the coarse voxels around it say wall.
    far = _plane_depth(pose, 1.05)
    out = fus.update(np.full((H, W), CHAIR, np.uint16), far, INTR, pose, {NOVEL})
    _, pic_far = _labels_with_picture(pose, far)
    assert (out[~pic_far] == CHAIR).all()


def _world_z(pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World z (height) of every pixel."""
    v, u = np.mgrid[0:H, 0:W]
    cam = np.stack([(u - INTR.cx) / INTR.fx * depth, (v - INTR.cy) / INTR.fy * depth, depth], -1)
    return (cam @ pose[:3, :3].T + pose[:3, 3])[..., 2]


def test_touching_coplanar_novel_ids_are_one_object_and_others_stay_apart():
    """A window's panes and frame, clustered apart (two novel ids), are published as one
    id from the frame that shows them together; two pictures that touch at a corner, and
    a window that meets the (novel) ceiling at a right angle, keep their own ids (the
    coarse map is off: a fresh surface would take its neighbourhood's id from it)."""
    other = NOVEL + 1
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x, z = _world_x(pose, depth), _world_z(pose, depth)

    def labelled(first, second):
        lab = np.full((H, W), WALL, np.uint16)
        lab[first] = NOVEL
        lab[second] = other
        return lab

    window = (np.abs(x) < 0.4) & (np.abs(z) < 0.3)
    panes = (np.abs(x) < 0.3) & (np.abs(z) < 0.2)
    for share, merged in ((0.2, True), (0.0, False)):
        fus = LabelFusion(LabelFusionConfig(touch_share=share, coarse_voxel_size=0.0))
        out = fus.update(labelled(window & ~panes, panes), depth, INTR, pose, {NOVEL, other})
        if merged:  # the panes (the smaller region) are published as the frame's id
            assert fus.aliases == {other: NOVEL} and not (out == other).any()
            assert (out[panes] == NOVEL).mean() > 0.95
            out = fus.update(labelled(window & ~panes, panes), depth, INTR, pose,
                             {NOVEL, other})
            assert not (out == other).any() and (out[panes] == NOVEL).mean() > 0.95
        else:
            assert fus.aliases == {} and (out[panes] == other).mean() > 0.9

    # Two pictures side by side that touch along 5 cm of their outlines.
    left = (x > -0.5) & (x <= 0.0) & (np.abs(z) < 0.3)
    right = (x > 0.0) & (x < 0.5) & (z > 0.25) & (z < 0.5)
    fus = LabelFusion(LabelFusionConfig(touch_share=0.2, coarse_voxel_size=0.0))
    out = fus.update(labelled(left, right), depth, INTR, pose, {NOVEL, other})
    assert fus.aliases == {}
    assert (out[right] == other).mean() > 0.8 and (out[left] == NOVEL).mean() > 0.8

    # A window right under the ceiling: their border is a third of the window's outline
    # and continuous in depth (the room's corner), but the planes are 90 degrees apart.
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones((H, W))], -1)
    rays = rays @ pose[:3, :3].T
    with np.errstate(divide="ignore"):
        t_ceiling = np.where(rays[..., 2] > 0, 0.3 / rays[..., 2], np.inf)
    corner = np.minimum(depth, t_ceiling).astype(np.float32)
    ceiling = t_ceiling < depth
    xc, zc = _world_x(pose, corner), _world_z(pose, corner)
    under = ~ceiling & (np.abs(xc) < 0.3) & (zc > 0.0)
    fus = LabelFusion(LabelFusionConfig(touch_share=0.2, coarse_voxel_size=0.0))
    out = fus.update(labelled(ceiling, under), corner, INTR, pose, {NOVEL, other})
    assert fus.aliases == {}
    assert (out[under] == other).mean() > 0.8 and (out[ceiling] == NOVEL).mean() > 0.8


def test_a_frame_with_its_sill_is_no_plane_and_joins_the_panes_it_touches():
    """A window's frame seen with its sill sticking out of the wall is no plane: its
    best-fit "normal" is 60 degrees from the panes', so the plane test kept the two ids
    apart (the tuning seeds' windows). A region that is no plane has no
    normal to compare, and the shared border decides; a sloped but planar region at
    that angle (the sill alone) still keeps its id."""
    from neurncd_ros.core.camera import backproject
    frame_id, panes_id = NOVEL, NOVEL + 1
    pose = _wall_pose(0.0)
    flat = _plane_depth(pose)
    x, z = _world_x(pose, flat), _world_z(pose, flat)
    panes = (np.abs(x) < 0.3) & (np.abs(z) < 0.2)
    side = (x > 0.3) & (x < 0.4) & (np.abs(z) < 0.2)
    sill = (np.abs(x) < 0.4) & (z < -0.2) & (z > -0.4)
    depth = flat.copy()  # the sill comes out of the wall, 2 m per m below the panes
    depth[sill] = flat[sill] * (1 - 2.0 * (-0.2 - z[sill]))
    points = np.zeros((H, W, 3))
    valid_points, valid = backproject(depth, INTR)
    points[valid] = valid_points

    def plane(mask):
        ev, vec = np.linalg.eigh(np.cov(points[mask].T))
        return ev[0] / ev[1], vec[:, 0]

    ratio, n_frame = plane(side | sill)
    _, n_panes = plane(panes)
    angle = np.degrees(np.arccos(abs(float(n_frame @ n_panes))))
    assert ratio > 0.2 and angle > 45  # the case of the tuning seeds' windows
    # touch_plane_ratio 1 takes every region for a plane, as the rule did before.
    for frame, plane_ratio, joined in ((side | sill, 0.1, True), (sill, 0.1, False),
                                       (side | sill, 1.0, False)):
        lab = np.full((H, W), WALL, np.uint16)
        lab[frame], lab[panes] = frame_id, panes_id
        fus = LabelFusion(LabelFusionConfig(touch_share=0.2, coarse_voxel_size=0.0,
                                            touch_plane_ratio=plane_ratio))
        out = fus.update(lab, depth, INTR, pose, {frame_id, panes_id})
        if joined:  # the panes, the larger region, keep their id
            assert fus.aliases == {frame_id: panes_id}
            assert (out[frame] == panes_id).mean() > 0.9
        else:
            assert fus.aliases == {} and (out[frame] == frame_id).mean() > 0.9


@pytest.mark.parametrize("mapped", [True, False])
def test_a_new_id_beside_the_surface_the_map_knows_joins_its_id(mapped):
    """The ceiling seen again from a new viewpoint, with new surface beside the part seen
    before: the frame calls all of it by a new id, and the map keeps the old id on the
    part it knows (five frames of votes). The old id is in the fused labels only, so the
    touching rule on the frame's own labels never saw the two touch, and too little of
    the new id lies on the old surface for ``alias_share``; ``touch_mapped`` tests the
    fused labels' pairs too, and the new id joins the old one (the tuning seed 505's
    ceiling: 104, then 118 from frame 29 on)."""
    old_id, new_id = NOVEL, NOVEL + 1
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x = _world_x(pose, depth)
    seen = (x > -0.5) & (x < -0.2)     # the part seen before
    now = (x > -0.5) & (x < 0.7)       # the frame's new id covers it and the new part
    assert seen.sum() < 0.4 * now.sum()  # below alias_share: that rule stays out
    fus = LabelFusion(LabelFusionConfig(coarse_voxel_size=0.0, touch_mapped=mapped))
    before = np.where(seen, old_id, 0).astype(np.uint16)  # the rest unseen: no votes
    for _ in range(5):
        fus.update(before, depth, INTR, pose, {old_id})
    after = np.where(now, new_id, WALL).astype(np.uint16)
    out = fus.update(after, depth, INTR, pose, {old_id, new_id})
    if mapped:
        assert fus.aliases == {new_id: old_id}
        assert (out[now] == old_id).mean() > 0.95
    else:
        assert fus.aliases == {}
        assert (out[seen] == old_id).mean() > 0.9 and (out[now & ~seen] == new_id).mean() > 0.9


def test_touch_mapped_leaves_two_ids_the_frame_does_not_show_apart():
    """``touch_mapped`` tests a frame's novel id against one only the map gives. Two ids
    the frame shows neither of (it calls their surface wall) are not its pairs: the map
    shows them side by side in every such frame, and where its coarse voxels widen them
    over the wall between (a new depth, fresh voxels) they touch. A picture and the
    window beside it, shown apart in every frame that showed them, stay apart."""
    picture, window = NOVEL, NOVEL + 1
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x = _world_x(pose, depth)
    lab = np.full((H, W), WALL, np.uint16)
    lab[(x > -0.6) & (x < -0.03)] = picture  # 6 cm of wall between them
    lab[(x > 0.03) & (x < 0.6)] = window
    fus = LabelFusion(LabelFusionConfig())
    for _ in range(4):
        fus.update(lab, depth, INTR, pose, {picture, window})
    wall = np.full((H, W), WALL, np.uint16)
    farther = _plane_depth(pose, 1.035)  # another fine voxel: the coarse map fills the gap
    touched = 0
    for _ in range(3):
        out = fus.update(wall, farther, INTR, pose, {picture, window})
        touched += bool((out[:, 1:] != out[:, :-1])[(out[:, 1:] >= NOVEL_ID_START)
                                                    & (out[:, :-1] >= NOVEL_ID_START)].any())
    assert fus.aliases == {}
    assert touched >= 2  # the case: the two touched in the fused labels


def test_touching_evidence_counts_a_frame_once():
    """``alias_frame_share`` counts frames: a pair that becomes another pair within a
    frame, as one of its ids is aliased there, is no second frame of evidence. Three ids
    touch in one frame (a window's top A, panes B and frame C); A joins B first, so the
    pair A-C is B-C too: C touched B in 1 of the 3 frames that showed it, under the share
    of 0.5, and keeps its id."""
    a, b, c = NOVEL, NOVEL + 1, NOVEL + 2
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x, z = _world_x(pose, depth), _world_z(pose, depth)
    low = (z > -0.5) & (z < 0)
    apart = np.full((H, W), WALL, np.uint16)  # B and C with wall between
    apart[low & (x > -0.7) & (x < 0.07)], apart[low & (x > 0.13) & (x < 0.6)] = b, c
    fus = LabelFusion(LabelFusionConfig(coarse_voxel_size=0.0, alias_share=0.0,
                                        touch_mapped=False))
    for _ in range(2):
        fus.update(apart, depth, INTR, pose, {b, c})
    lab = np.full((H, W), WALL, np.uint16)
    lab[(z >= 0) & (z < 0.5) & (x > -0.7) & (x < 0.6)] = a
    lab[low & (x > -0.7) & (x < 0.1)], lab[low & (x >= 0.1) & (x < 0.6)] = b, c
    fus.update(lab, depth, INTR, pose, {a, b, c})
    assert fus.aliases == {a: b}


def test_touching_ids_keep_the_id_shown_longer():
    """An object that appears as a sliver (here a window's panes, one frame alone) and
    whose bulk gets a fresh, larger id in the next frame keeps the id it was shown with
    first: the newer id is published as the older, not the smaller as the larger."""
    panes_id, frame_id = NOVEL + 1, NOVEL + 2
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x, z = _world_x(pose, depth), _world_z(pose, depth)
    window = (np.abs(x) < 0.4) & (np.abs(z) < 0.3)
    panes = (np.abs(x) < 0.25) & (np.abs(z) < 0.15)
    assert (window & ~panes).sum() > 2 * panes.sum()  # the new id is the larger region
    live = {panes_id, frame_id}
    fus = LabelFusion(LabelFusionConfig(touch_share=0.2, coarse_voxel_size=0.0))
    first = np.full((H, W), WALL, np.uint16)
    first[panes] = panes_id
    fus.update(first, depth, INTR, pose, live)
    both = first.copy()
    both[window & ~panes] = frame_id
    out = fus.update(both, depth, INTR, pose, live)
    assert fus.aliases == {frame_id: panes_id}
    assert (out[window] == panes_id).mean() > 0.95 and not (out == frame_id).any()


@pytest.mark.parametrize("rule", ["touch", "share"])
def test_one_frame_does_not_rename_an_established_id(rule):
    """An id shown for many frames is not renamed by one frame's evidence: here a
    clustering error gives a piece of a picture beside a window the ceiling's id (touch:
    the piece touches the window in the wall's plane) or gives the window the ceiling's
    id (share: the window's surface, under another id, with the window's own id absent).
    With ``alias_frame_share`` 0 one frame renames the ceiling for good, as before; by
    default it keeps its id, and a new id with the same evidence is still renamed at once
    (the parts of one object)."""
    window_id, ceiling_id = NOVEL, NOVEL + 1
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x, z = _world_x(pose, depth), _world_z(pose, depth)
    window = (np.abs(x) < 0.3) & (np.abs(z) < 0.3)
    piece = (x >= 0.3) & (x < 0.45) & (np.abs(z) < 0.25)  # touches the window's side
    # The ceiling, seen elsewhere: another camera looking up at the plane z = 1.2.
    up = look_at(np.array([3.0, 0.0, 0.0]), np.array([3.0, 0.01, 1.0]))
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones((H, W))], -1)
    up_depth = (1.2 / (rays @ up[:3, :3].T)[..., 2]).astype(np.float32)
    ceiling_only = np.full((H, W), ceiling_id, np.uint16)
    wall_window = np.where(window, window_id, WALL).astype(np.uint16)
    if rule == "touch":
        bad = wall_window.copy()
        bad[piece] = ceiling_id
        cfg = dict(alias_share=0.0, touch_share=0.2)
    else:
        bad = np.where(window, ceiling_id, WALL).astype(np.uint16)
        cfg = dict(alias_share=0.4, touch_share=0.0)
    live = {window_id, ceiling_id}
    for share, renamed in ((0.0, True), (0.5, False)):
        fus = LabelFusion(LabelFusionConfig(coarse_voxel_size=0.0, alias_frame_share=share,
                                            **cfg))
        for _ in range(6):
            fus.update(wall_window, depth, INTR, pose, live)
            fus.update(ceiling_only, up_depth, INTR, up, live)
        fus.update(bad, depth, INTR, pose, live)
        assert (ceiling_id in fus.aliases) == renamed, fus.aliases
        for _ in range(12):  # the ceiling's own old votes fade under the renamed ones
            out = fus.update(ceiling_only, up_depth, INTR, up, live)
        assert (out == (window_id if renamed else ceiling_id)).mean() > 0.95
    # A new id with the same evidence in its first frame is a part of the window.
    fresh = NOVEL + 2
    fus = LabelFusion(LabelFusionConfig(coarse_voxel_size=0.0, **cfg))
    for _ in range(6):
        fus.update(wall_window, depth, INTR, pose, live)
    fus.update(np.where(bad == ceiling_id, fresh, bad).astype(np.uint16), depth, INTR, pose,
               live | {fresh})
    assert fus.aliases == {fresh: window_id}


def test_a_new_piece_between_two_established_ids_renames_neither():
    """A new id's piece touches two established ids in one frame (the TV and, through a
    clustering error, the ceiling's id on the wall): the piece becomes one of them, and
    neither established id is renamed through it (the evidence is counted for the ids
    as published, not for the piece's own new id)."""
    tv, ceiling, piece = NOVEL, NOVEL + 1, NOVEL + 5
    pose = _wall_pose(0.0)
    depth = _plane_depth(pose)
    x, z = _world_x(pose, depth), _world_z(pose, depth)
    band = np.abs(z) < 0.3
    left, mid, right = band & (x < -0.1), band & (np.abs(x) <= 0.1), band & (x > 0.1)
    live = {tv, ceiling, piece}
    fus = LabelFusion(LabelFusionConfig(coarse_voxel_size=0.0, alias_share=0.0))
    for _ in range(6):
        lab = np.full((H, W), WALL, np.uint16)
        lab[left], lab[right] = tv, ceiling
        lab[mid] = WALL
        fus.update(lab, depth, INTR, pose, live)
    lab[mid] = piece
    fus.update(lab, depth, INTR, pose, live)
    assert set(fus.aliases) == {piece} and fus.aliases[piece] in (tv, ceiling)
