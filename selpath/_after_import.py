"""Run a callback once a module has been imported, whether it was imported before or after the callback was asked for
(a post-import hook: what ``wrapt.register_post_import_hook`` does, without importing wrapt's dependencies).

``import selpath`` uses it to register the ``.selpath`` accessor the moment xarray is imported, so that a program
that never touches a labelled array never pays for xarray, and one that does finds the accessor there.
"""

from __future__ import annotations

import importlib.abc
import sys
from collections.abc import Callable
from types import ModuleType


class _AfterImport(importlib.abc.MetaPathFinder):
    """A finder that finds nothing itself: it asks the finders after it for ``name``'s spec and wraps the loader's
    ``exec_module`` so that ``callback`` runs once the module has been executed; then it removes itself."""

    def __init__(self, name: str, callback: Callable[[], None]):
        self.name, self.callback = name, callback

    def find_spec(self, fullname: str, path, target: ModuleType | None = None):
        if fullname != self.name:
            return None
        if self in sys.meta_path:
            sys.meta_path.remove(self)  # once, and never asked again while the others look
        spec = None
        for finder in list(sys.meta_path):
            find = getattr(finder, "find_spec", None)
            spec = find(fullname, path, target) if find is not None else None
            if spec is not None:
                break
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec  # not found (the import fails as it would have) or a loader we cannot wrap
        exec_module, callback = spec.loader.exec_module, self.callback

        def exec_then_call(module: ModuleType) -> None:
            exec_module(module)
            callback()

        spec.loader.exec_module = exec_then_call  # this spec's own loader object, made for this import
        return spec


def after_import(name: str, callback: Callable[[], None]) -> None:
    """Call ``callback()`` now if the module ``name`` is imported already, else right after it is first imported."""
    if name in sys.modules:
        callback()
    else:
        sys.meta_path.insert(0, _AfterImport(name, callback))
