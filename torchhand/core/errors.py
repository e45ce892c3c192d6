"""The errors a user can fix: a bad argument or input, an optional dependency not
installed. The command line reports them in one line (exit status 2); any other
exception is a bug in torchhand and keeps its traceback (:mod:`torchhand.app.cli`)."""

from __future__ import annotations

__all__ = ["UsageError", "UnknownName", "MissingExtra", "EXTRAS"]

#: The optional dependencies and the extra of ``pyproject.toml`` that installs each.
EXTRAS = {"ray": "ray", "pybullet": "physics", "fcl": "fcl", "pygel3d": "rig", "smplx": "bench", "rerun": "viz"}


class UsageError(ValueError):
    """A bad argument, value or input file; the message names it and what is expected."""


class UnknownName(UsageError, LookupError):
    """A name that is not among the known ones (a model, a sequence, ...); the message
    lists them."""


class MissingExtra(ImportError):
    """An optional dependency is not installed: ``what`` needs ``module``, which
    ``pip install 'torchhand[extra]'`` installs."""

    def __init__(self, what: str, module: str, extra: str = None):
        self.extra = extra or EXTRAS.get(module, module)
        super().__init__(f"{what} needs {module}: pip install 'torchhand[{self.extra}]'", name=module)
