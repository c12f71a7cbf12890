"""Discovery's state survives a restart: saved, read back weights-only, and continued, a
discoverer labels the next views exactly as the one that never stopped (the same novel
ids for the same objects; a restarted node once reused id 101, tv before, for a picture)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from neurncd_ros import config, synth
from neurncd_ros.core.discovery.state import load_state, save_state
from neurncd_ros.core.engine.discovery import DiscoveryStage
from neurncd_ros.core.engine.offline import OfflineEngine
from neurncd_ros.core.torchfile import TorchFileError


@pytest.fixture(scope="module")
def views():
    """The mapper stage's views of a held-out scene with novel objects (every labelled
    frame of 3 s at 160x120)."""
    cfg = config.default()
    engine = OfflineEngine(cfg)
    frames = synth.generate(2001, 90, synth.SynthConfig(width=160, height=120))
    return cfg, [o.view for o in engine.run(frames, progress=False)]


def test_a_continued_state_labels_as_the_discoverer_that_never_stopped(views, tmp_path):
    cfg, vs = views
    k = len(vs) // 2
    path = tmp_path / "state" / "discovery.pt"
    node_cfg = dataclasses.replace(cfg.discovery_node, state_path=str(path))
    running = DiscoveryStage(cfg, node_cfg)
    for v in vs[:k]:
        running.label_view(v)
    assert running.save_state() and path.is_file()
    assert running.discoverer.novel_ids, "the scene's first half shows novel objects"
    restarted = DiscoveryStage(cfg, node_cfg)  # reads the file; continues on the spec
    fresh = DiscoveryStage(cfg, cfg.discovery_node)
    differs = 0
    for v in vs[k:]:
        a, b = running.label_view(v), restarted.label_view(v)
        np.testing.assert_array_equal(a.labels, b.labels)
        assert a.classes == b.classes
        c = fresh.label_view(v)
        differs += not np.array_equal(a.labels, c.labels)
    assert restarted.health.counts["note.state"] == 1
    assert differs, "a discoverer without the state labels the second half differently"


def test_a_state_for_other_classes_is_not_continued(views, tmp_path):
    cfg, vs = views
    path = tmp_path / "discovery.pt"
    node_cfg = dataclasses.replace(cfg.discovery_node, state_path=str(path))
    stage = DiscoveryStage(cfg, node_cfg)
    stage.label_view(vs[0])
    state = stage.discoverer.state()
    state["made_for"]["__dict__"] = [[k, [1, 2] if k == "channel_to_id" else v]
                                     for k, v in state["made_for"]["__dict__"]]
    save_state(path, {"discovery": state})
    other = DiscoveryStage(cfg, node_cfg)
    other.label_view(vs[0])
    assert other.health.problems["state_not_continued"] == 1
    assert other.discoverer.memory_len == stage.discoverer.memory_len  # afresh, one view


def test_a_bad_state_file_is_one_clear_error(tmp_path):
    path = tmp_path / "discovery.pt"
    path.write_bytes(b"\x00" * 100)
    cfg = config.default()
    node_cfg = dataclasses.replace(cfg.discovery_node, state_path=str(path))
    with pytest.raises(TorchFileError, match="discovery state"):
        DiscoveryStage(cfg, node_cfg)
    save_state(path, {"discovery": {}})
    assert load_state(path)["version"] == 1


def test_a_refused_state_is_kept_aside_and_a_folder_is_refused_at_start(views, tmp_path):
    """A state not continued (another configuration: one mistyped -p) is kept beside as
    <path>.not-continued, not overwritten by the next save; a folder as the path is an
    error at start, not a traceback at the first save after minutes of labelling."""
    cfg, vs = views
    path = tmp_path / "discovery.pt"
    node_cfg = dataclasses.replace(cfg.discovery_node, state_path=str(path))
    stage = DiscoveryStage(cfg, node_cfg)
    stage.label_view(vs[0])
    stage.save_state()
    saved = path.read_bytes()
    other_cfg = config.load(None, {"modulation.colour_weight": 0.0})
    other = DiscoveryStage(other_cfg, node_cfg)
    other.label_view(vs[0])
    assert other.health.problems["state_not_continued"] == 1
    assert "colour_weight" in other.state_refused and "not-continued" in other.state_refused
    other.save_state()
    assert (tmp_path / "discovery.pt.not-continued").read_bytes() == saved
    folder = dataclasses.replace(cfg.discovery_node, state_path=str(tmp_path))
    with pytest.raises(TorchFileError, match="is a folder: give a file path"):
        DiscoveryStage(cfg, folder)


def _saving_stage(cfg, vs, tmp_path):
    """A stage saving to tmp_path/discovery.pt every 30 s of its clock (``now[0]``), after
    labelling the first 3 views: (stage, now, path)."""
    now = [0.0]
    path = tmp_path / "discovery.pt"
    node_cfg = dataclasses.replace(cfg.discovery_node, state_path=str(path), save_period_s=30)
    stage = DiscoveryStage(cfg, node_cfg, clock=lambda: now[0])
    for v in vs[:3]:
        stage.label_view(v)
    return stage, now, path


def test_the_state_is_saved_once_due_while_idle_and_only_when_something_is_new(views,
                                                                               tmp_path):
    """The node asks for a save after each view and while idle: what the last views
    discovered reaches the file once save_period_s has passed even if no view follows (a
    SIGKILL after the input stopped lost novel ids 105-108), and an idle node does not
    rewrite an unchanged state every period."""
    cfg, vs = views
    stage, now, path = _saving_stage(cfg, vs, tmp_path)
    assert not stage.save_state(force=False) and not path.exists()  # not due yet
    now[0] = 31.0  # idle since: the next idle call saves
    assert stage.save_state(force=False) and path.is_file()
    now[0] = 100.0
    assert not stage.save_state(force=False), "nothing new: no rewrite"
    stage.label_view(vs[3])
    assert stage.save_state(force=False)
    assert stage.health.counts["state_saves"] == 2


def test_reset_forgets_the_discovered_classes_as_a_new_start_would(views):
    """The discovery node's ~/reset (a new room into running nodes): the stage labels the
    next views exactly as a stage that never saw the first ones, novel ids from 100."""
    cfg, vs = views
    k = len(vs) // 2
    stage = DiscoveryStage(cfg, cfg.discovery_node)
    for v in vs[:k]:
        stage.label_view(v)
    assert stage.discoverer.novel_ids
    stage.reset()
    assert not stage.discoverer.novel_ids
    fresh = DiscoveryStage(cfg, cfg.discovery_node)
    for v in vs[k:]:
        a, b = stage.label_view(v), fresh.label_view(v)
        np.testing.assert_array_equal(a.labels, b.labels)
        assert a.classes == b.classes
    assert stage.health.counts["resets"] == 1


def test_a_reset_during_a_save_is_saved_next(views, tmp_path, monkeypatch):
    """The node's ~/reset runs on its service thread, the idle save on the labelling
    thread: a reset that came while the old room was being written was marked saved, so
    a node killed before the next view restarted with the old room's novel ids."""
    from neurncd_ros.core.discovery import state

    cfg, vs = views
    stage, now, path = _saving_stage(cfg, vs, tmp_path)
    assert stage.discoverer.novel_ids
    write = state.save_state

    def write_then_reset(*args, **kwargs):
        write(*args, **kwargs)
        stage.reset()  # the service call, while the worker is still in save_state
    monkeypatch.setattr(state, "save_state", write_then_reset)
    now[0] = 31.0
    assert stage.save_state(force=False)
    monkeypatch.setattr(state, "save_state", write)
    now[0] = 62.0
    assert stage.save_state(force=False), "the reset was never saved"
    fresh = DiscoveryStage(cfg, stage.node_cfg)
    fresh.set_spec(stage.spec)
    assert fresh.state_refused is None and not fresh.discoverer.novel_ids
