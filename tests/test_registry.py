"""The name -> class registry and the `pipe.plugins` entry points behind it."""

from __future__ import annotations

from importlib.metadata import EntryPoint

import pytest

from pipe import registry
from pipe.errors import PipeError
from pipe.evaluation.methods import METHODS
from pipe.registry import Registry


@pytest.fixture
def entry_points(monkeypatch):
    """Pretend these entry points are installed; the real ones come back afterwards."""
    def install(*points: EntryPoint) -> None:
        monkeypatch.setattr(registry, "entry_points", lambda group: [p for p in points if p.group == group])
        registry.load_plugins.cache_clear()

    yield install
    monkeypatch.undo()
    registry.load_plugins.cache_clear()


def test_builtin_methods_are_registered_in_order():
    assert list(METHODS) == ["pipe", "oracle", "oracle_clean", "nearest", "gpr", "blackbox", "mean"]
    assert METHODS["gpr"].__name__ == "GPR" and "mean" in METHODS and "kriging" not in METHODS


def test_an_unknown_name_lists_what_there_is():
    with pytest.raises(PipeError, match=r"unknown method 'kriging'; available: \['pipe', 'oracle'"):
        METHODS["kriging"]


def test_a_name_taken_twice_or_missing_is_refused():
    things = Registry("thing")

    @things.register
    class A:
        name = "a"

    with pytest.raises(PipeError, match="two things are named 'a'"):
        things.register(type("B", (), {"name": "a"}))
    with pytest.raises(TypeError, match="needs a `name`"):
        things.register(type("C", (), {}))
    assert things.register(A) is A and list(things) == ["a"]


def test_a_plugin_module_reloaded_registers_its_classes_again(tmp_path, monkeypatch):
    """importlib.reload (a notebook's autoreload) defines a plugin's classes anew: the new ones replace theirs."""
    import importlib

    (tmp_path / "thing_registry.py").write_text("from pipe.registry import Registry\nTHINGS = Registry('thing')\n")
    (tmp_path / "thing_plugin.py").write_text("from thing_registry import THINGS\n\n@THINGS.register\n"
                                              "class A:\n    name = 'a'\n")
    monkeypatch.syspath_prepend(tmp_path)
    plugin = importlib.import_module("thing_plugin")
    first = plugin.A
    importlib.reload(plugin)
    things = importlib.import_module("thing_registry").THINGS
    assert plugin.A is not first and things["a"] is plugin.A and list(things) == ["a"]
    with pytest.raises(PipeError, match="two things are named 'a': thing_plugin and tests"):
        things.register(type("A", (), {"name": "a", "__module__": "tests"}))


def test_a_plugin_that_fails_to_import_is_named(entry_points):
    entry_points(EntryPoint("broken", "no_such_pipe_plugin_module", registry.ENTRY_POINT_GROUP),
                 EntryPoint("other", "json", "some.other.group"))
    with pytest.raises(PipeError, match="the pipe plugin 'broken' .* fails to import: ModuleNotFoundError"):
        METHODS["mean"]
    assert registry.plugin_config_modules() == []


def test_a_plugin_package_with_configs_joins_the_search_path(entry_points):
    entry_points(EntryPoint("builtin", "pipe", registry.ENTRY_POINT_GROUP),           # pipe.conf exists
                 EntryPoint("noconf", "pipe.data", registry.ENTRY_POINT_GROUP))      # pipe.data.conf does not
    assert registry.plugin_config_modules() == ["pipe.conf"]
    assert registry.load_plugins() == ("builtin", "noconf")
