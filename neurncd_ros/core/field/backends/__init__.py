"""Field backends: each one is a module with a config class and a ``FieldModel``.

A backend registers itself by name with its config class::

    @register("fast", FastConfig)
    class FastModel(FieldModel):
        def __init__(self, cfg: FastConfig, channels: int, shared: MapperConfig,
                     generator: torch.Generator) -> None: ...

The mapper builds ``get(mapper_cfg.backend).model(...)``; the configuration
schema gets one section ``mapper.<name>`` per registered backend. The two
built-in backends are imported at the end of this module.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from .base import FieldModel, RayBatch


@dataclasses.dataclass(frozen=True)
class Backend:
    """A registered backend: its name, config class and model class."""

    name: str
    config: type
    model: type


_REGISTRY: dict[str, Backend] = {}


def register(name: str, config: type) -> Callable[[type], type]:
    """Class decorator registering a ``FieldModel`` subclass under ``name``."""
    if not name.isidentifier():
        raise ValueError(f"backend name must be an identifier, got {name!r}")
    if not dataclasses.is_dataclass(config):
        raise TypeError(f"backend {name!r}: config must be a param(...) dataclass")

    def wrap(model: type) -> type:
        if not issubclass(model, FieldModel):
            raise TypeError(f"backend {name!r}: {model.__name__} is not a FieldModel")
        if name in _REGISTRY and _REGISTRY[name].model is not model:
            raise ValueError(f"backend {name!r} is already registered "
                             f"({_REGISTRY[name].model.__name__})")
        _REGISTRY[name] = Backend(name, config, model)
        return model

    return wrap


def unregister(name: str) -> None:
    """Remove a registered backend (tests register temporary ones)."""
    _REGISTRY.pop(name, None)


def names() -> tuple[str, ...]:
    """Registered backend names, in registration order."""
    return tuple(_REGISTRY)


def get(name: str) -> Backend:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown field backend {name!r}; registered: "
                         + ", ".join(_REGISTRY)) from None


def config_classes() -> dict[str, type]:
    """Backend name -> its config class (the ``mapper.<name>`` sections)."""
    return {b.name: b.config for b in _REGISTRY.values()}


from . import fast, reference  # noqa: E402,F401  (the built-ins register themselves)

__all__ = ["Backend", "FieldModel", "RayBatch", "config_classes", "get", "names", "register",
           "unregister"]
