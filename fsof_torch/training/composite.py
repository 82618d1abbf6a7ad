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
            Any name works; the ``nn.Module`` terms are submodules under ``terms.<name>``, except
            where the name cannot be a submodule's (empty, containing ``"."``, not a string, or an
            attribute of ``nn.ModuleDict`` such as ``"values"``): then under ``terms._term<i>``,
            ``i`` the term's position. Results always carry the given names.

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
        self._functions: dict[str, object] = {}   # the terms that are not modules
        self._keys: dict[str, str] = {}           # term name -> its key in self.terms
        entries = []
        for name, entry in terms.items():
            if not (isinstance(entry, (tuple, list)) and len(entry) == 2 and callable(entry[1])):
                raise TypeError(f"terms[{name!r}]: expected (weight, callable term), got {entry!r}")
            weight, term = entry
            self.weights[name] = check_number(weight, f"terms[{name!r}] weight", nonnegative=True)
            self._names[name] = _accepted_names(term)
            entries.append((name, term))
        probe = nn.ModuleDict()
        taken = {name for name in self.weights if _module_key(name, probe)}
        modules = {}
        for i, (name, term) in enumerate(entries):
            if not isinstance(term, nn.Module):
                self._functions[name] = term
                continue
            key = name
            if not _module_key(name, probe):
                key = f"_term{i}"
                while key in taken:  # (a given name that happens to read "_term<i>")
                    key = "_" + key
                taken.add(key)
            self._keys[name] = key
            modules[key] = term
        self.terms = nn.ModuleDict(modules)

    def _term(self, name: str):
        return self.terms[self._keys[name]] if name in self._keys else self._functions[name]

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


def _module_key(name: object, probe: nn.ModuleDict) -> bool:
    """Whether ``name`` can key a submodule of ``probe`` (an empty ``nn.ModuleDict``)."""
    return isinstance(name, str) and name != "" and "." not in name and not hasattr(probe, name)


def _accepted_names(term: object) -> tuple[set[str], bool]:
    """Keyword names ``term`` accepts after ``flows``, and whether it takes ``**kwargs``."""
    fn = term.forward if isinstance(term, nn.Module) else term
    params = list(inspect.signature(fn).parameters.values())[1:]
    takes_all = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
    names = {p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                   inspect.Parameter.KEYWORD_ONLY)}
    return names, takes_all
