"""Field backends: each one is a module with a config class and a ``FieldModel``.

A backend registers itself by name with its config class::

    @register("fast", FastConfig)
    class FastModel(FieldModel):
        def __init__(self, cfg: FastConfig, channels: int, shared: MapperConfig,
                     generator: torch.Generator) -> None: ...

The mapper builds ``get(mapper_cfg.backend).model(...)``; the configuration
schema gets one section ``mapper.<name>`` per registered backend. The two
built-in backends are imported here; a backend module imports ``register``
from :mod:`.registry` (not from this package, which imports the backends).
"""

from __future__ import annotations

from .base import FieldModel, RayBatch
from .registry import Backend, config_classes, get, names, register, unregister
from . import fast, reference  # noqa: F401  (the built-ins register themselves)

__all__ = ["Backend", "FieldModel", "RayBatch", "config_classes", "get", "names", "register",
           "unregister"]
