"""Hydra search-path plugin: the configs of installed pipe plugins (`pipe.plugins` entry points) join the
search path of pipe's apps, so `encoder=<name>` finds an installed package's `conf/encoder/<name>.yaml`."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

PIPE_CONFIG = "pkg://pipe.conf"


class PipePluginsSearchPath(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        if not any(element.path == PIPE_CONFIG for element in search_path.get_path()):
            return   # another Hydra app in the same environment: leave it alone
        from pipe.registry import plugin_config_modules

        for module in plugin_config_modules():
            search_path.append(provider="pipe-plugin", path=f"pkg://{module}")


def register() -> None:
    """Register the plugin with Hydra explicitly. Hydra finds it by scanning the `hydra_plugins` namespace,
    which fails where pipe is an editable install (setuptools' import hook cannot be listed); registering
    twice is harmless."""
    from hydra.core.plugins import Plugins

    Plugins.instance().register(PipePluginsSearchPath)
