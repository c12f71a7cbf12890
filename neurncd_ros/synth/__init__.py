"""The project's synthetic world: procedural RGB-D rooms with exact ground truth.

Outside the science core on purpose: the core never depends on where frames
come from, and the generator is a data source like a bag or a dataset folder.

    from neurncd_ros import synth
    for frame in synth.generate(seed=3, frames=300, cfg=synth.SynthConfig()):
        ...

``seeds`` holds the one split of scene seeds into train / validation / tune / test.
"""

from .generator import SynthConfig, frames_at, generate, intrinsics_of, room_of, trajectory

__all__ = ["SynthConfig", "generate", "frames_at", "room_of", "trajectory", "intrinsics_of"]
