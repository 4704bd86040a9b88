"""SPEC 1 lazy loading from a package's stub: the ``.pyi`` beside a package's ``__init__.py`` lists what it gives (its
submodules and the names it re-exports, ``from .module import name as name``) for type checkers and editors, and at
run time ``lazy_loader.attach_stub`` reads the same file, so each name is imported when first used and the two lists
cannot differ. The stub's ``__all__`` is the package's API (the submodules are attributes, not API)."""

from __future__ import annotations

import ast
import os
from collections.abc import Callable

import lazy_loader


def attach(package: str, file: str) -> tuple[Callable[[str], object], Callable[[], list[str]], list[str]]:
    """``__getattr__``, ``__dir__`` and ``__all__`` for the package ``package`` whose ``__init__.py`` is ``file``."""
    getattr_, dir_, _ = lazy_loader.attach_stub(package, file)
    with open(os.path.splitext(file)[0] + ".pyi", encoding="utf-8") as stub:
        tree = ast.parse(stub.read())
    api = next(ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
               and any(isinstance(target, ast.Name) and target.id == "__all__" for target in node.targets))
    return getattr_, dir_, list(api)
