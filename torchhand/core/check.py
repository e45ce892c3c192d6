"""Input validation at the public boundary: shapes, dtypes, devices, finiteness.

One module for every layer, after kornia's ``core/check.py``: each function raises a
clear error that names the argument and what was expected, and returns nothing (or
the checked tensor). Shapes are written as tuples of sizes::

    check_tensor(theta, "theta", ("B", 37))              # exactly 2 dims, the last 37
    check_tensor(points, "points", ("...", "N", 3))      # any leading dims, then (N, 3)

An ``int`` must match, a ``str`` (the dimension's name, shown in the message) or
``None`` matches any size, and a leading ``"..."`` admits any number of leading
dimensions.

Settings (plain numbers and names) are checked the same way, once, where an object is
made::

    check_number(max_distance, "max_distance", low=0, unit="mm")   # a number > 0
    check_int(max_pixels, "max_pixels", low=1)                      # an int >= 1
    check_choice(metric, "metric", ("point-to-point", "point-to-plane"))

Checks cost host syncs (``finite=True`` reads every value) and Python time, so they
run once, where data enters; inner loops that call public functions with data the
library made itself wrap them in :func:`skip_checks`.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any, Iterator, Optional, Sequence, Union

import torch

__all__ = ["check_tensor", "check_same", "check_broadcast", "check_index", "check_number", "check_int",
           "check_choice", "fmt_shape", "skip_checks", "checks_enabled"]

Dim = Union[int, str, None]

_state = threading.local()


def checks_enabled() -> bool:
    """False inside :func:`skip_checks` (in this thread)."""
    return getattr(_state, "depth", 0) == 0


@contextlib.contextmanager
def skip_checks() -> Iterator[None]:
    """Skip every check of this module in the enclosed block (this thread only).

    For hot loops that pass tensors the library created itself (solver iterations,
    renders inside a tracker step); never around user input.
    """
    _state.depth = getattr(_state, "depth", 0) + 1
    try:
        yield
    finally:
        _state.depth -= 1


def fmt_shape(shape: Sequence[Any]) -> str:
    """``(4, 37)`` for a torch.Size or a shape spec (``None`` shows as ``*``)."""
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _shape_ok(got: Sequence[int], want: Sequence[Dim]) -> bool:
    want = list(want)
    if want and want[0] == "...":
        want = want[1:]
        if len(got) < len(want):
            return False
        got = got[len(got) - len(want):]
    elif len(got) != len(want):
        return False
    return all(not isinstance(w, int) or isinstance(w, bool) or w == g for g, w in zip(got, want))


def check_tensor(
    x: Any,
    name: str,
    shape: Optional[Sequence[Dim]] = None,
    *,
    spec: Optional[str] = None,
    dtype: Optional[torch.dtype] = None,
    floating: bool = False,
    integer: bool = False,
    device: Optional[Union[torch.device, str]] = None,
    finite: bool = False,
) -> Any:
    """Raise unless ``x`` is a tensor of the given shape, dtype and device.

    Args:
        x: the value to check.
        name: the argument's name, used in the messages.
        shape: a shape spec (module docstring); None checks no shape.
        spec: the shape as the message should show it (default: from ``shape``), e.g.
            ``"(B, V, 3) or (V, 3)"``.
        dtype: the exact dtype required.
        floating: a floating-point dtype is required.
        integer: an integer dtype (not bool) is required.
        device: the device ``x`` must be on (an unindexed ``cuda`` matches any CUDA device).
        finite: no NaN or inf (reads every value: a host sync).
    Returns:
        ``x``.
    Raises:
        TypeError: not a tensor, or the wrong dtype.
        ValueError: the wrong shape or device, or non-finite values.
    """
    if not checks_enabled():
        return x
    want = spec if spec is not None else (fmt_shape(shape) if shape is not None else None)
    if not isinstance(x, torch.Tensor):
        shown = f" of shape {want}" if want else ""
        raise TypeError(f"{name} must be a torch.Tensor{shown}, got {type(x).__name__}")
    if shape is not None and not _shape_ok(tuple(x.shape), shape):
        raise ValueError(f"{name} must have shape {want}, got {fmt_shape(tuple(x.shape))}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"{name} must have dtype {dtype}, got {x.dtype}")
    if floating and not x.is_floating_point():
        raise TypeError(f"{name} must have a floating point dtype, got {x.dtype}")
    if integer and (x.is_floating_point() or x.is_complex() or x.dtype == torch.bool):
        raise TypeError(f"{name} must have an integer dtype (int64), got {x.dtype}")
    if device is not None and not _same_device(x.device, device):
        raise ValueError(f"{name} is on {x.device} but must be on {device}; move it with .to()")
    if finite and x.is_floating_point() and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return x


def check_index(x: torch.Tensor, name: str, size: int, what: str = "rows") -> None:
    """Raise unless every entry of the integer tensor ``x`` lies in ``[0, size)`` (a host sync)."""
    if not checks_enabled() or x.numel() == 0:
        return
    lo, hi = int(x.min()), int(x.max())
    if lo < 0 or hi >= size:
        raise ValueError(f"{name} must index {what} in [0, {size}), got range [{lo}, {hi}]")


def check_same(names: Sequence[str], tensors: Sequence[torch.Tensor], *, dtype: bool = True,
               device: bool = True) -> None:
    """Raise if the tensors disagree in dtype or device (torch would fail less clearly)."""
    if not checks_enabled():
        return
    first, ref = names[0], tensors[0]
    for name, x in zip(names[1:], tensors[1:]):
        if dtype and x.dtype != ref.dtype:
            raise TypeError(f"{name} has dtype {x.dtype} but {first} has dtype {ref.dtype}; they must match")
        if device and x.device != ref.device:
            raise ValueError(f"{name} is on {x.device} but {first} is on {ref.device}; they must match")


def check_broadcast(names: Sequence[str], shapes: Sequence[Sequence[int]]) -> None:
    """Raise unless the shapes broadcast against each other (plain Python: much
    cheaper than ``torch.broadcast_shapes`` per call)."""
    if not checks_enabled():
        return
    ndim = max((len(s) for s in shapes), default=0)
    for k in range(1, ndim + 1):
        sizes = {int(s[-k]) for s in shapes if len(s) >= k and int(s[-k]) != 1}
        if len(sizes) > 1:
            pairs = ", ".join(f"{n} {fmt_shape(tuple(s))}" for n, s in zip(names, shapes))
            raise ValueError(f"leading dimensions do not broadcast: {pairs}")


def _same_device(a: torch.device, b: Union[torch.device, str]) -> bool:
    b = torch.device(b)
    return a.type == b.type and (a.index is None or b.index is None or a.index == b.index)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_number(value: Any, name: str, *, low: Optional[float] = None, inclusive: bool = False,
                 high: Optional[float] = None, unit: str = "", none: bool = False) -> None:
    """A finite real number (not a bool) above ``low`` (``>= low`` with ``inclusive``)
    and at most ``high``; ``none``: None is admitted too. The message names ``name``,
    the bound, the ``unit`` and the value given."""
    if none and value is None:
        return
    want = []
    if low is not None:
        want.append(f"{'>=' if inclusive else '>'} {low:g}")
    if high is not None:
        want.append(f"<= {high:g}")
    ok = _is_number(value) and value == value and abs(value) != float("inf")
    if ok and low is not None:
        ok = value >= low if inclusive else value > low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        what = "a finite number" + (" " + " and ".join(want) if want else "") + (f" ({unit})" if unit else "")
        raise ValueError(f"{name} must be {what}{' or None' if none else ''}, got {value!r}")


def check_int(value: Any, name: str, *, low: Optional[int] = None) -> None:
    """An int (not a bool) of at least ``low``; the message names ``name`` and the value."""
    if not (isinstance(value, int) and not isinstance(value, bool) and (low is None or value >= low)):
        raise ValueError(f"{name} must be an int" + (f" >= {low}" if low is not None else "") + f", got {value!r}")


def check_choice(value: Any, name: str, choices: Sequence[Any]) -> None:
    """One of ``choices``; the message lists them."""
    if value not in tuple(choices):
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
