"""Errors of options forwarded in a mapping (``fit_options``, ``curve_options``, ...), named as the
caller gave them.

A function that forwards ``fit_options={"scale": -1.0}`` to a fit gets the fit's error,
``scale: expected a finite number > 0, got -1.0``, which names the option as the fit takes it: where
the forwarding function has an argument of that name (the refiner's ``scale``,
``detect_freespace``'s ``relative_threshold``), the message points at the wrong, valid argument.
:func:`keyed_errors` names the key of the mapping instead: ``fit_options['scale']: ...``.
"""

from __future__ import annotations

import contextlib
from typing import Iterator, Mapping

__all__ = ["keyed_errors"]


@contextlib.contextmanager
def keyed_errors(options: Mapping[str, object] | None, name: str) -> Iterator[None]:
    """Within it, a TypeError or ValueError whose message starts with a key of ``options``
    (``"scale: ..."``) is raised again, of the same type, as ``"{name}['scale']: ..."``; any other
    error passes unchanged."""
    try:
        yield
    except (TypeError, ValueError) as err:
        key, _, rest = str(err).partition(": ")
        if not options or key not in options or type(err) not in (TypeError, ValueError):
            raise
        raise type(err)(f"{name}[{key!r}]: {rest}") from err
