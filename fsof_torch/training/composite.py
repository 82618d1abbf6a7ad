"""A weighted sum of training loss terms, each reported separately (:class:`CompositeLoss`).

The terms are those of :mod:`fsof_torch.training.losses` or any callable ``term(flows, **inputs)``
returning a scalar; each is fed, from one batch dict, the inputs its ``forward`` names.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence

from torch import Tensor, nn

from .._check import check_number

__all__ = ["CompositeLoss"]


class CompositeLoss(nn.Module):
    """A weighted sum of loss terms, each reported separately.

    Args:
        terms: ``{name: (weight, term)}``; ``term(flows, **inputs)`` returns a scalar. Each term
            receives, from the inputs given to ``forward``, those whose names are parameters of
            its ``forward`` (or of the function itself), so one batch dict can feed all terms.
            Each weight is a finite number >= 0: a bool, a string or any other non-number raises
            TypeError, NaN, inf or a negative weight ValueError, naming ``terms[name]``.

    ``forward(flows, inputs=None, **more)`` -> ``(total, values)``: the weighted sum (a scalar
    with gradient) and ``{name: unweighted value}`` (detached scalars).

    Example:
        >>> from fsof_torch.training.losses import FreespaceFlowLoss, UnsupervisedFlowLoss
        >>> loss = CompositeLoss({"unsupervised": (1.0, UnsupervisedFlowLoss()),
        ...                       "freespace": (0.1, FreespaceFlowLoss())})
        >>> total, values = loss(flows, batch, flows_backward=flows_bw)  # doctest: +SKIP
    """

    def __init__(self, terms: Mapping[str, tuple[float, object]]) -> None:
        super().__init__()
        if not isinstance(terms, Mapping) or not terms:
            raise TypeError(f"terms: expected a non-empty dict {{name: (weight, term)}}, got {terms!r}")
        self.weights: dict[str, float] = {}
        self._names: dict[str, tuple[set[str], bool]] = {}
        modules = {}
        for name, entry in terms.items():
            if not (isinstance(entry, (tuple, list)) and len(entry) == 2 and callable(entry[1])):
                raise TypeError(f"terms[{name!r}]: expected (weight, callable term), got {entry!r}")
            weight, term = entry
            self.weights[name] = check_number(weight, f"terms[{name!r}] weight", nonnegative=True)
            if isinstance(term, nn.Module):
                modules[name] = term
            else:
                setattr(self, f"_fn_{name}", term)
            self._names[name] = _accepted_names(term)
        self.terms = nn.ModuleDict(modules)

    def _term(self, name: str):
        return self.terms[name] if name in self.terms else getattr(self, f"_fn_{name}")

    def forward(self, flows: Tensor | Sequence[Tensor], inputs: Mapping[str, object] | None = None,
                **more: object) -> tuple[Tensor, dict[str, Tensor]]:
        given = {**dict(inputs or {}), **more}
        total = 0.0
        values: dict[str, Tensor] = {}
        for name, weight in self.weights.items():
            accepted, takes_all = self._names[name]
            kwargs = given if takes_all else {k: v for k, v in given.items() if k in accepted}
            value = self._term(name)(flows, **kwargs)
            values[name] = value.detach()
            total = total + weight * value
        return total, values


def _accepted_names(term: object) -> tuple[set[str], bool]:
    """Keyword names ``term`` accepts after ``flows``, and whether it takes ``**kwargs``."""
    fn = term.forward if isinstance(term, nn.Module) else term
    params = list(inspect.signature(fn).parameters.values())[1:]
    takes_all = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
    names = {p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                   inspect.Parameter.KEYWORD_ONLY)}
    return names, takes_all
