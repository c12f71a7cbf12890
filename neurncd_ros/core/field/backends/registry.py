"""The registry of field backends: name -> (config class, ``FieldModel`` class).

Its own module so that a backend module imports ``register`` from here and the
package ``backends`` imports the built-in backends, without either importing
the other while it is half initialised (no import circle).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from .base import FieldModel


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
    """The backend registered under ``name``; a ValueError lists the registered ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown field backend {name!r}; registered: "
                         + ", ".join(_REGISTRY)) from None


def config_classes() -> dict[str, type]:
    """Backend name -> its config class (the ``mapper.<name>`` sections)."""
    return {b.name: b.config for b in _REGISTRY.values()}
