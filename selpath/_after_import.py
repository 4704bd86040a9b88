"""Run a callback once a module has been imported, whether it was imported before or after the callback was asked for
(a post-import hook: what ``wrapt.register_post_import_hook`` does, without importing wrapt's dependencies).

``import selpath`` uses it to register the ``.selpath`` accessor the moment xarray is imported, so that a program
that never touches a labelled array never pays for xarray, and one that does finds the accessor there.
"""

from __future__ import annotations

import importlib.abc
import sys
import warnings
from collections.abc import Callable
from types import ModuleType


class _AfterImport(importlib.abc.MetaPathFinder):
    """A finder that finds nothing itself: it asks the finders after it for ``name``'s spec and has its loader call
    ``callback`` once that module has been executed. It stays on ``sys.meta_path`` until then (a spec asked for and
    never loaded, ``importlib.util.find_spec(name)``, leaves it there), and never changes what the loader does for
    any other module (a zip or frozen importer loads many with one object)."""

    def __init__(self, name: str, callback: Callable[[], None]):
        self.name, self.callback, self.done = name, callback, False

    def find_spec(self, fullname: str, path, target: ModuleType | None = None):
        if fullname != self.name or self.done or fullname in sys.modules:
            return None
        spec = None
        for finder in list(sys.meta_path):
            find = None if finder is self else getattr(finder, "find_spec", None)
            spec = find(fullname, path, target) if find is not None else None
            if spec is not None:
                break
        loader = getattr(spec, "loader", None)
        if loader is None or not hasattr(loader, "exec_module") or "exec_module" in getattr(loader, "__dict__", {}):
            return spec  # not found (the import fails as it would have), or a loader we cannot, or did, wrap
        exec_module = loader.exec_module

        def exec_then_call(module: ModuleType) -> None:
            if module.__name__ != self.name or self.done:
                exec_module(module)
                return
            self.done = True
            del loader.exec_module  # the loader's own again, for whatever it loads next
            sys.meta_path = [f for f in sys.meta_path if f is not self]  # a new list: a loop elsewhere keeps its own
            exec_module(module)
            try:
                self.callback()
            except Exception as exc:  # noqa: BLE001 - the module imported; only what the callback adds is missing
                warnings.warn(f"after importing {self.name}: {type(exc).__name__}: {exc}", RuntimeWarning,
                              stacklevel=2)

        try:
            loader.exec_module = exec_then_call
        except (AttributeError, TypeError):  # a loader without an instance dict: the module loads, unhooked
            pass
        return spec


def after_import(name: str, callback: Callable[[], None]) -> None:
    """Call ``callback()`` now if the module ``name`` is imported already, else right after it is first imported."""
    if name in sys.modules:
        callback()
    else:
        sys.meta_path = [_AfterImport(name, callback), *sys.meta_path]
