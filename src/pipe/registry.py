"""Plugins from other packages, and a plain name -> class registry (as in timm or torchvision).

A package extends pipe by declaring an entry point in the `pipe.plugins` group that names one of its
modules:

    [project.entry-points."pipe.plugins"]
    my_plugin = "my_pipe_plugin"

Hydra then finds the package's configs (`my_pipe_plugin/conf/<encoder|head|model>/<name>.yaml`, with a
`conf/__init__.py`) through the search-path plugin in `hydra_plugins.pipe_searchpath`, so that
`python train.py encoder=<name>` works once the package is installed. Importing the module registers
whatever it registers by name, e.g. evaluation methods (`pipe.evaluation.methods.METHODS`).
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Iterator
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import Generic, TypeVar

from pipe.errors import PipeError

ENTRY_POINT_GROUP = "pipe.plugins"
T = TypeVar("T", bound=type)


def plugin_entry_points() -> list[EntryPoint]:
    """The installed packages' `pipe.plugins` entry points, by name."""
    return sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: ep.name)


def plugin_config_modules() -> list[str]:
    """The config packages (`<module>.conf`) of the installed plugins that have one, for Hydra's search path."""
    modules = []
    for ep in plugin_entry_points():
        name = f"{ep.module}.conf"
        try:
            found = importlib.util.find_spec(name) is not None
        except ImportError:   # the plugin's own module does not import: reported when it is loaded
            found = False
        if found:
            modules.append(name)
    return modules


@cache
def load_plugins() -> tuple[str, ...]:
    """Import every installed plugin module once (which registers its classes); their names."""
    for ep in plugin_entry_points():
        try:
            importlib.import_module(ep.module)
        except Exception as exc:   # a broken third-party package: name it, no traceback wall
            raise PipeError(f"the pipe plugin {ep.name!r} ({ep.value}, from the `{ENTRY_POINT_GROUP}` entry points) "
                            f"fails to import: {type(exc).__name__}: {exc}") from None
    return tuple(ep.name for ep in plugin_entry_points())


def _where(cls: type) -> tuple[str, str]:
    """The module and qualified name a class is defined under."""
    return cls.__module__, cls.__qualname__


class Registry(Generic[T]):
    """Classes of one kind by name; installed plugins are loaded before a name is looked up."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._classes: dict[str, T] = {}

    def register(self, cls: T) -> T:
        """Class decorator: register `cls` under its `name` attribute. The same class defined again (its module
        reloaded, or run again as a script) replaces the one registered; another class of that name is refused."""
        name = getattr(cls, "name", None)
        if not isinstance(name, str) or not name:
            raise TypeError(f"{cls.__qualname__} needs a `name` to be registered as a {self.kind}")
        if name in self._classes and _where(self._classes[name]) != _where(cls):
            raise PipeError(f"two {self.kind}s are named {name!r}: {self._classes[name].__module__} and "
                            f"{cls.__module__}")
        self._classes[name] = cls
        return cls

    def names(self) -> list[str]:
        load_plugins()
        return list(self._classes)

    def __getitem__(self, name: str) -> T:
        if name not in self.names():
            raise PipeError(f"unknown {self.kind} {name!r}; available: {self.names()}")
        return self._classes[name]

    def __contains__(self, name: object) -> bool:
        return name in self.names()

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())
