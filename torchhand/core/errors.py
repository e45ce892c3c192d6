"""The errors a user can fix: a bad argument or input, an optional dependency not
installed. The command line reports them in one line (exit status 2), and a failed
sequence of a run in one line of its summary; any other exception is a bug in torchhand
and keeps its traceback (:func:`user_error` decides, :mod:`torchhand.app.cli`)."""

from __future__ import annotations

import traceback
from pathlib import Path
from typing import Optional

__all__ = ["UsageError", "UnknownName", "MissingExtra", "EXTRAS", "user_error", "is_user_error", "is_bug", "failure_text"]

_PACKAGE = Path(__file__).resolve().parents[1]

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


def user_error(err: BaseException) -> Optional[str]:
    """The one-line message of an error the user can fix, or None for a bug.

    User errors: :class:`UsageError` (a bad argument or input, e.g. ``SequenceError``), a
    ``ValueError`` raised by torchhand's own checks (not one from deep inside numpy or
    torch), an ``OSError`` (a path that is missing, taken or unreadable; a cluster that
    does not answer), and an optional dependency that is not installed
    (:class:`MissingExtra`, the import of a module of :data:`EXTRAS`, or an
    ``ImportError`` whose message says what to ``pip install``). Everything else
    (``TypeError``, ``KeyError``, ``AttributeError``, an import of torchhand's own
    modules...) is a bug."""
    if isinstance(err, (UsageError, OSError, MissingExtra)):
        return str(err)
    if isinstance(err, ImportError):
        module = (err.name or "").split(".")[0]
        if module in EXTRAS:
            return str(MissingExtra("this command", module))
        return str(err) if "pip install" in str(err) else None  # torchhand's own message naming the package
    if isinstance(err, ValueError) and _raised_by_torchhand(err):
        return str(err)
    return None


def is_user_error(err: BaseException) -> bool:
    """An error that says it is the user's wherever it is raised: a :class:`UsageError`
    (a bad argument or input, a frame without a hand in view), an ``OSError``, an
    optional dependency not installed."""
    return isinstance(err, (UsageError, OSError, MissingExtra)) or (
        isinstance(err, ImportError) and user_error(err) is not None)


def is_bug(err: BaseException) -> bool:
    """Neither the user's error (:func:`is_user_error`) nor a ``ValueError`` of
    torchhand's own checks (which inside a task may be the data's or a broken invariant):
    a bug in torchhand."""
    return not is_user_error(err) and not (isinstance(err, ValueError) and _raised_by_torchhand(err))


def failure_text(err: BaseException) -> str:
    """What a run's summary and the console say of a sequence that failed with ``err``
    (call it where the error is caught). Inside a task a ``ValueError`` of torchhand's
    checks may be the data's fault or a broken invariant, so only the errors that say
    they are the user's (:func:`is_user_error`) are one line, their message. Any other
    ``ValueError`` raised by torchhand keeps its type and the innermost frames of its
    traceback; anything else is a bug: its type and message, the request to report it,
    and the traceback's innermost frames."""
    if is_user_error(err):
        return user_error(err)
    frames = "".join(traceback.format_exception(type(err), err, err.__traceback__, limit=-6))
    if not is_bug(err):
        return f"{type(err).__name__}: {err}\n{frames}"
    return f"{type(err).__name__}: {err} (a bug in torchhand: please report it with this traceback)\n{frames}"


def _raised_by_torchhand(err: BaseException) -> bool:
    """The innermost frame of the error's traceback is torchhand's code."""
    tb = err.__traceback__
    if tb is None:
        return True
    while tb.tb_next is not None:
        tb = tb.tb_next
    return Path(tb.tb_frame.f_code.co_filename).resolve().is_relative_to(_PACKAGE)
