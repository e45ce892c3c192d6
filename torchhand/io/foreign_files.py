"""Reading files that others published without running their code.

Public datasets ship YAML and pickles. Both formats can name Python objects to build, so
a crafted file could run code when loaded with the standard loaders. Here:

- :func:`read_yaml` uses PyYAML's safe loader, which builds plain data only, and accepts
  one Python tag besides, ``!!python/tuple``, as a list (some DexYCB exports write their
  calibration matrices with it); any other Python tag is refused.
- :func:`read_pickle` admits builtin containers and numbers and numpy arrays (what the
  HO-3D annotation pickles hold, Python 2 pickles included); a pickle that asks for any
  other class or function is refused before anything of it is built.

Every refusal is a :class:`ForeignFileError` naming the file and what it asked for.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import yaml

from torchhand.core.errors import UsageError

__all__ = ["ForeignFileError", "read_yaml", "read_pickle", "PICKLE_CLASSES"]


class ForeignFileError(UsageError):
    """A published file that cannot be read safely or at all; the message names it."""


class _Loader(yaml.SafeLoader):
    """The safe loader with ``!!python/tuple`` read as a list."""


_Loader.add_constructor("tag:yaml.org,2002:python/tuple", lambda loader, node: loader.construct_sequence(node))


def read_yaml(path) -> Any:
    """The plain data of a YAML file (``!!python/tuple`` as a list); a file that names
    any other Python object, or is not YAML, is a :class:`ForeignFileError`."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            return yaml.load(f, Loader=_Loader)
    except yaml.constructor.ConstructorError as err:
        raise ForeignFileError(f"{path}: {err.problem} (only plain data and !!python/tuple are read)") from None
    except yaml.YAMLError as err:
        raise ForeignFileError(f"{path}: not a YAML file ({err})") from None


#: (module, name) of the classes and functions a pickle may ask for: numpy's array and
#: scalar reconstruction (numpy 1 and 2 name their module differently), the builtin
#: containers that are not pickle opcodes of their own, and ``_codecs.encode``, with which
#: protocol-2 pickles written by Python 3 store bytes (an array's data) as text
PICKLE_CLASSES = frozenset(
    [(m, n) for m in ("numpy.core.multiarray", "numpy._core.multiarray") for n in ("_reconstruct", "scalar")]
    + [(m, "_frombuffer") for m in ("numpy.core.numeric", "numpy._core.numeric")]
    + [("numpy", "ndarray"), ("numpy", "dtype")]
    + [("builtins", n) for n in ("set", "frozenset", "bytearray", "complex", "slice", "range")]
    + [("__builtin__", n) for n in ("set", "frozenset", "bytearray", "complex", "slice")]
    + [("_codecs", "encode")])


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, path: Path):
        super().__init__(file, encoding="latin1")  # Python 2 pickles of numpy arrays
        self.path = path

    def find_class(self, module: str, name: str):
        if (module, name) not in PICKLE_CLASSES:
            raise ForeignFileError(f"{self.path}: the pickle asks for {module}.{name}; only builtin containers and "
                                   "numpy arrays are read (a pickle that names anything else is refused, not run)")
        if module == "__builtin__":
            module = "builtins"
        return super().find_class(module, name)


def read_pickle(path) -> Any:
    """The builtin containers, numbers and numpy arrays of a pickle file; one that asks
    for any other class or function is a :class:`ForeignFileError`, raised before it is
    built."""
    path = Path(path)
    with open(path, "rb") as f:
        try:
            return _Unpickler(f, path).load()
        except ForeignFileError:
            raise
        except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as err:
            raise ForeignFileError(f"{path}: not a readable pickle ({type(err).__name__}: {err})") from None
