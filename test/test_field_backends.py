"""Field backends as plug-ins and the mapper without hidden global state.

A third backend is registered from this file (one config class + one model),
configured through the schema and trained and rendered by an unchanged Mapper;
two mappers in one process give identical, independent results; the training
thread pauses for renders, and a render can be cancelled between chunks; map
files record every section they were built with.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import types

import numpy as np
import pytest
import torch
from torch import nn

from neurncd_ros import config, synth
from neurncd_ros.core.field import backends, losses, samplers
from neurncd_ros.core.field.backends.base import FieldModel, render_samples
from neurncd_ros.core.field.backends.fast import FastConfig, FastModel
from neurncd_ros.core.field.fields import EmbeddingField, linear
from neurncd_ros.core.field.keyframes import KeyframeConfig
from neurncd_ros.core.field.mapper import Mapper, MapperConfig, RenderCancelled
from neurncd_ros.core.params import ConfigError, param

torch.set_num_threads(1)
S = 9


@pytest.fixture(scope="module")
def frames():
    return list(synth.generate(5, 8, synth.SynthConfig(width=64, height=48, fps=3.0)))


def _embedding(frame, seed: int) -> np.ndarray:
    """Logits that follow the colour (learnable) plus noise, at half resolution."""
    rng = np.random.default_rng(seed)
    rgb = frame.rgb[::2, ::2].astype(np.float32) / 255.0
    emb = rng.normal(0.0, 0.3, rgb.shape[:2] + (S,)).astype(np.float32)
    emb[..., :3] += 4.0 * rgb
    return emb


def _fed(mapper: Mapper, frames) -> Mapper:
    for i, f in enumerate(frames):
        assert mapper.add_keyframe(f, _embedding(f, i), force=True)
    return mapper


def _small(seed: int = 4, **mapper) -> Mapper:
    return Mapper(MapperConfig(seed=seed, **mapper), S, backend_cfg=FastConfig(
        rays_per_iteration=128, plane_cell_sizes=[0.16, 0.04]))


# ------------------------------------------------------------------ a third backend

@dataclasses.dataclass(frozen=True)
class ConstantConfig:
    """Constant density with linear colour and embedding heads (test backend)."""

    rays_per_iteration: int = param(64, "training rays per iteration", lo=1, hi=4096)
    samples: int = param(8, "stratified samples per ray", lo=2, hi=64)
    lr: float = param(2e-2, "Adam learning rate", lo=0.0, hi=1.0)


class ConstantField(EmbeddingField):
    def __init__(self, channels: int, generator: torch.Generator) -> None:
        super().__init__()
        self.channels = channels
        self.head = linear(3, 3 + channels, generator)
        self.log_sigma = nn.Parameter(torch.zeros(()))

    def geometry(self, x):
        h = self.head(x)
        return self.log_sigma.exp().expand(x.shape[0]), h[:, 3:], h[:, :3]

    def colour(self, feature, d):
        return torch.sigmoid(feature)


class ConstantModel(FieldModel):
    def __init__(self, cfg: ConstantConfig, channels: int, shared, generator) -> None:
        super().__init__()
        self.cfg, self.lambda_embedding = cfg, shared.lambda_embedding
        self.field = ConstantField(channels, generator)
        self.rays_per_iteration = cfg.rays_per_iteration
        self.train_samples_per_ray = self.render_samples_per_ray = cfg.samples

    def losses(self, batch, near, far, generator):
        t = samplers.stratified(near, far, self.cfg.samples, generator)
        out = render_samples(self.field, batch.origins, batch.dirs, t)
        lp = losses.photometric(out["rgb"], batch.rgb)
        le = losses.embedding_kl(batch.embedding, out["embedding"])
        return {"total": lp + self.lambda_embedding * le, "photometric": lp, "embedding": le,
                "fine_rgb_mse": ((out["rgb"] - batch.rgb) ** 2).mean().detach()}

    def render_rays(self, origins, dirs, near, far, depth=None):
        t = samplers.stratified(near, far, self.cfg.samples, None)
        return render_samples(self.field, origins, dirs, t)

    def param_groups(self):
        return [{"params": list(self.parameters()), "lr": self.cfg.lr}]


def test_a_registered_backend_is_configured_trained_rendered_and_saved(frames, tmp_path):
    backends.register("constant", ConstantConfig)(ConstantModel)
    try:
        # The schema has its section at once: nested in the file, dotted in ROS.
        cfg = config.from_nested({"mapper": {"backend": "constant",
                                             "constant": {"samples": 6}}})
        assert cfg.section("mapper.constant") == ConstantConfig(samples=6)
        assert cfg.to_flat()["mapper.constant.samples"] == 6
        assert "mapper.constant.lr" in config.markdown_table()
        with pytest.raises(ConfigError, match=r"mapper\.constant\.samples: 1 is out of range"):
            config.from_flat({"mapper.constant.samples": 1})
        m = _fed(Mapper.from_config(cfg, S), frames[:4])
        assert isinstance(m.model, ConstantModel) and m.model.rays_per_iteration == 64
        first = m.step(1)
        later = m.step(40)
        assert later["photometric"] < 0.8 * first["photometric"], (first, later)
        f = frames[5]
        out = m.render(f.pose, f.intrinsics, 12, 16)
        assert out["embedding"].shape == (12, 16, S) and np.isfinite(out["rgb"]).all()
        assert out["entropy"].min() >= 0 and out["entropy"].max() <= math.log(S) + 1e-5
        m.save(tmp_path / "constant.pt")
        again = Mapper.load(tmp_path / "constant.pt")
        assert again.backend_cfg == ConstantConfig(samples=6)
        assert np.array_equal(again.render(f.pose, f.intrinsics, 12, 16)["embedding"],
                              out["embedding"])
    finally:
        backends.unregister("constant")
    assert "mapper.constant" not in config.default().sections
    with pytest.raises(ConfigError, match=r"mapper\.backend: 'constant' is not allowed"):
        config.from_nested({"mapper": {"backend": "constant"}})
    with pytest.raises(ValueError, match="unknown field backend 'constant'"):
        Mapper(MapperConfig(backend="constant"), S)


def test_registry_refuses_what_is_not_a_backend():
    with pytest.raises(TypeError, match="not a FieldModel"):
        backends.register("thing", ConstantConfig)(ConstantField)
    with pytest.raises(ValueError, match="already registered"):
        backends.register("fast", ConstantConfig)(ConstantModel)
    with pytest.raises(TypeError, match="FastConfig"):
        Mapper(MapperConfig(backend="fast"), S, backend_cfg=ConstantConfig())
    assert backends.names()[:2] == ("fast", "reference")
    assert backends.get("fast").model is FastModel


# ------------------------------------------------------------------ no global state

def test_two_mappers_in_one_process_do_not_affect_each_other(frames):
    torch.manual_seed(1)
    np.random.seed(1)
    global_state = torch.get_rng_state(), np.random.get_state()[1].copy()
    threads = torch.get_num_threads()
    a = _fed(_small(num_threads=threads + 1), frames[:4])
    alone = [a.step(1)["total"] for _ in range(6)]
    f = frames[5]
    view_a = a.render(f.pose, f.intrinsics, 12, 16)
    # Nothing global was drawn from or set: not the generators, not the thread count.
    assert torch.equal(torch.get_rng_state(), global_state[0])
    assert np.array_equal(np.random.get_state()[1], global_state[1])
    assert torch.get_num_threads() == threads

    b = _fed(_small(), frames[:4])
    other = _fed(_small(seed=9), frames[2:6])
    together = []
    for _ in range(6):
        together.append(b.step(1)["total"])
        torch.manual_seed(123)  # whoever touches the global generator...
        torch.rand(1000)
        other.step(1)  # ...or trains another mapper in between changes nothing
    assert together == alone
    assert np.array_equal(b.render(f.pose, f.intrinsics, 12, 16)["embedding"],
                          view_a["embedding"])
    assert other.step(1)["total"] != together[-1]  # a different seed is another mapper

    a.reset()  # reseeds: as built
    _fed(a, frames[:4])
    assert [a.step(1)["total"] for _ in range(6)] == alone


# ------------------------------------------------------------------ pause and cancel

class ChunkProbe(threading.Event):
    """A cancel event that records the mapper's iterations at every check and reports
    itself set after ``after`` checks (None: never)."""

    def __init__(self, mapper: Mapper, after: int | None = None) -> None:
        super().__init__()
        self.mapper, self.after, self.seen = mapper, after, []

    def is_set(self) -> bool:
        self.seen.append(self.mapper.iterations)
        return self.after is not None and len(self.seen) > self.after


def _wait_for_iterations(m: Mapper, n: int) -> None:
    """Wait until background training has passed n iterations (fails if it stops)."""
    done = threading.Event()

    def watch():
        while m.running and m.iterations < n:
            done.wait(0.01)
        done.set()

    threading.Thread(target=watch, daemon=True).start()
    assert done.wait(60) and m.iterations >= n, (m.iterations, m.last_error)


def test_render_can_be_cancelled_between_chunks(frames):
    m = _fed(_small(render_chunk=1024), frames[:2])  # 14 rays per chunk
    f = frames[3]
    probe = ChunkProbe(m, after=3)
    with pytest.raises(RenderCancelled, match="after 42 of 768 rays"):
        m.render(f.pose, f.intrinsics, 24, 32, cancel=probe)
    assert len(probe.seen) == 4
    stop = threading.Event()
    stop.set()
    with pytest.raises(RenderCancelled):
        m.render(f.pose, f.intrinsics, cancel=stop)
    # A cancelled render releases its pause: training goes on afterwards.
    m.start()
    try:
        _wait_for_iterations(m, 3)
        with pytest.raises(RenderCancelled):
            m.render(f.pose, f.intrinsics, 24, 32, cancel=ChunkProbe(m, after=2))
        _wait_for_iterations(m, m.iterations + 3)
    finally:
        m.stop()
    assert m.last_error is None


def test_training_pauses_for_renders_and_while_paused(frames):
    m = _fed(_small(render_chunk=1024), frames[:2])
    f = frames[3]
    m.start()
    try:
        _wait_for_iterations(m, 2)
        probe = ChunkProbe(m)
        m.render(f.pose, f.intrinsics, 24, 32, cancel=probe)  # yield_to_render
        assert len(probe.seen) > 50 and len(set(probe.seen)) == 1, probe.seen[:3]
        with m.paused():
            held = m.iterations
            with m.paused():  # pauses nest
                pass
            probe = ChunkProbe(m)
            for _ in range(3):
                m.render(f.pose, f.intrinsics, 24, 32, cancel=probe)
            assert m.iterations == held and set(probe.seen) == {held}
        _wait_for_iterations(m, held + 3)  # resumes after the last pause
        with m.paused():
            m.stop()  # stopping while paused does not wait for the pause
        assert not m.running
    finally:
        m.stop()
    assert m.last_error is None


# ------------------------------------------------------------------ construction, files

def test_from_config_takes_any_object_with_the_sections(frames):
    shipped = config.default()
    m = Mapper.from_config(shipped, S)
    assert m.cfg == shipped.mapper and m.keyframe_cfg == shipped.keyframes
    assert m.backend_cfg == FastConfig() and m.model.rays_per_iteration == 2048
    sections = {"mapper.fast": FastConfig(rays_per_iteration=64, hidden=16)}
    duck = types.SimpleNamespace(mapper=MapperConfig(seed=3),
                                 keyframes=KeyframeConfig(max_keyframes=2),
                                 section=sections.__getitem__)
    m = _fed(Mapper.from_config(duck, S), frames[:3])
    assert len(m.buffer) == 2 and m.model.rays_per_iteration == 64
    assert np.isfinite(m.step(1)["total"])


def test_map_file_records_every_section_and_refuses_old_versions(frames, tmp_path):
    m = Mapper(MapperConfig(seed=5, min_iterations_before_publish=3), S,
               keyframes=KeyframeConfig(max_keyframes=5, recent_window=2),
               backend_cfg=FastConfig(rays_per_iteration=96, hidden=16,
                                      plane_cell_sizes=[0.16, 0.08]))
    _fed(m, frames[:3]).step(2)
    path = tmp_path / "map.pt"
    m.save(path)
    again = Mapper.load(path)
    assert (again.cfg, again.keyframe_cfg, again.backend_cfg) == (m.cfg, m.keyframe_cfg,
                                                                   m.backend_cfg)
    changed = Mapper.load(path, rays_per_iteration=32, recent_window=1, near=0.1)
    assert changed.backend_cfg.rays_per_iteration == 32 and changed.backend_cfg.hidden == 16
    assert changed.keyframe_cfg.recent_window == 1 and changed.cfg.near == 0.1
    assert np.isfinite(changed.step(1)["total"])
    with pytest.raises(ConfigError, match="cannot be changed"):
        Mapper.load(path, backend="reference")
    with pytest.raises(ConfigError, match="no_such: unknown parameter"):
        Mapper.load(path, no_such=1)
    with pytest.raises(ConfigError, match=r"mapper\.fast\.hidden: 2 is out of range"):
        Mapper.load(path, hidden=2)
    state = torch.load(path, weights_only=True)
    state["version"] = 1
    torch.save(state, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="version 1 map; this neurncd reads version 2"):
        Mapper.load(tmp_path / "old.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a neurncd mapper file"):
        Mapper.load(tmp_path / "other.pt")
    # A truncated map (a copy cut short), random bytes, text: one clear line, no traceback
    # of torch's (the mapper node exits 2 with it).
    data = path.read_bytes()
    for name, blob in (("cut.pt", data[: len(data) // 3]), ("random.pt", bytes(range(256)) * 9),
                       ("text.pt", b"not a map\n"), ("empty.pt", b"")):
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(ValueError, match=f"^cannot read map {tmp_path / name}: "):
            Mapper.load(tmp_path / name)
