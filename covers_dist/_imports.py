"""Importing escnn and POT without the start-up work this package never uses.

Every Ray actor and every ``covers-dist`` process imports escnn (it builds a network) and the
clustering processes import POT (``ot``, for W1). At import, both pull in modules only some of
their functions need:

* escnn's ``escnn.group._numerical`` imports scikit-learn for ``randomized_svd``, which this package
  turns off (``covers_dist.models._escnn_compat``; escnn then uses its exact scipy fallback);
* POT's ``ot.lowrank`` and three modules of ``ot.gromov`` import scikit-learn for k-means and spectral
  initialisations of solvers this package does not call; both fall back when it is missing;
* escnn's ``escnn.nn.init`` imports ``scipy.stats`` for one initialiser
  (``deltaorthonormal_init``) this package does not call (POT imports ``scipy.stats`` itself, so
  only the processes without POT, the rollout workers and learners, are spared it).

Measured on a 2-core AMD EPYC: scikit-learn costs a process ~0.6 s under escnn and ~1.5 s under
POT; ``scipy.stats`` ~0.5 s. :func:`import_lightly` imports a module with an import finder in
front that refuses scikit-learn to exactly those importers (found on the importing thread's stack:
they take their fallback at once) and loads ``scipy.stats`` for ``escnn.nn.init`` lazily (on its
first attribute access, :class:`importlib.util.LazyLoader`). Any other import of these modules,
by this package's code or on another thread, is untouched: the calibrated rule's Ledoit-Wolf
estimate still imports scikit-learn when it runs.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import warnings
from types import ModuleType
from typing import Any

__all__ = ["import_lightly"]

#: importer (a module, or a package and its modules) -> the package refused to it; each of their
#: imports of it is guarded (``try: ... except ImportError``) and falls back
REFUSED = {"escnn.group._numerical": "sklearn", "ot": "sklearn"}
#: importer -> the module it gets as a lazy module (loaded on first attribute access)
DEFERRED = {"escnn.nn.init": "scipy.stats"}


def import_lightly(module: str) -> ModuleType:
    """``module`` (``"escnn.nn"``, ``"escnn.gspaces"``, ``"ot"``), imported with warnings silenced
    and without what :data:`REFUSED` and :data:`DEFERRED` name. Already imported: returned as is."""
    if module in sys.modules:
        return sys.modules[module]
    finder = _LightFinder()
    sys.meta_path.insert(0, finder)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return importlib.import_module(module)
    finally:
        sys.meta_path.remove(finder)


def _importer(wanted: dict[str, str], name: str) -> str | None:
    """The module on the importing thread's stack that :data:`wanted` lists for ``name``."""
    frame = sys._getframe(2)
    while frame is not None:
        who = frame.f_globals.get("__name__") or ""
        for importer, target in wanted.items():
            if (who == importer or who.startswith(importer + ".")) and (name == target or name.startswith(target + ".")):
                return who
        frame = frame.f_back
    return None


class _LightFinder:
    """A ``sys.meta_path`` finder that applies :data:`REFUSED` and :data:`DEFERRED`."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name.split(".")[0] in set(REFUSED.values()) and _importer(REFUSED, name):
            raise ImportError(f"{name} is not imported here (the importer's fallback is used)")
        if name in set(DEFERRED.values()) and _importer(DEFERRED, name):
            spec = _find_with_the_other_finders(self, name, path, target)
            if spec is not None and spec.loader is not None and hasattr(spec.loader, "exec_module"):
                spec.loader = importlib.util.LazyLoader(spec.loader)
            return spec
        return None


def _find_with_the_other_finders(me: Any, name: str, path: Any, target: Any) -> Any:
    for finder in sys.meta_path:
        if finder is me or not hasattr(finder, "find_spec"):
            continue
        spec = finder.find_spec(name, path, target)
        if spec is not None:
            return spec
    return None
