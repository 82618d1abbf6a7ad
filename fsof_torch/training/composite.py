"""A weighted sum of training loss terms, each reported separately (:class:`CompositeLoss`).

The terms are those of :mod:`fsof_torch.training.losses` or any callable ``term(flows, **inputs)``
returning a scalar; each is fed, from one batch dict, the inputs its ``forward`` names.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from .._check import check_number

__all__ = ["CompositeLoss"]


class CompositeLoss(nn.Module):
    """A weighted sum of loss terms, each reported separately.

    Args:
        terms: ``{name: (weight, term)}``; ``term(flows, **inputs)`` returns a scalar. Each term
            receives, from the inputs given to ``forward``, those whose names are parameters of
            its ``forward`` (or of the function itself; of the compiled module's ``forward`` for
            ``torch.compile(module)``; of its TorchScript schema for ``torch.jit.trace(module)``;
            none for a builtin whose signature cannot be read, such as ``torch.mean``: it is called
            with the flows alone), so one batch dict can feed all terms. The keywords a
            ``functools.partial`` term binds are its own: an input of that name is not passed
            (``partial(freespace_flow_loss, odometry="fit")`` fits, whatever odometry the batch
            holds); a partial of a module is fed the other inputs its ``forward`` names.
            Each weight is a finite number >= 0: a bool, a string or any other non-number raises
            TypeError, NaN, inf or a negative weight ValueError, naming ``terms[name]``. A 0-d
            tensor is read as its number, but one that requires grad (a learnable weight, whose
            gradient would be lost) raises TypeError.
            Any name works; the ``nn.Module`` terms are submodules under ``terms.<name>``, except
            where the name cannot be a submodule's (empty, containing ``"."``, not a string, or an
            attribute of ``nn.ModuleDict`` such as ``"values"``): then under ``terms._term<i>``,
            ``i`` the term's position. Results always carry the given names.

    ``forward(flows, inputs=None, **more)`` -> ``(total, values)``: the weighted sum (a scalar
    with gradient) and ``{name: unweighted value}`` (detached scalars; a term may return a tensor
    or a Python number). ``inputs`` is None or a mapping (a batch dict), else TypeError naming
    ``inputs``. A term of weight 0 is evaluated and reported but not added, so a diagnostic term
    that returns inf or NaN leaves the total as it is (where every weight is 0, or no weighted
    term carries a gradient, such as terms that return Python numbers, the total is one that
    ``backward()`` accepts where gradients are on, and no gradient reaches the flows). A TypeError from a
    term's call (an input it needs and was not given, one it does not take) is raised again
    naming ``terms[name]``; a term whose value is not one number (one of
    ``reduction="none"`` on a batch of more than one) is a ValueError naming it; a value of
    shape (1,) counts as a scalar, and the total then has that shape.

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
        self._names: dict[str, tuple[set[str], bool, frozenset[str]]] = {}
        self._functions: dict[str, object] = {}   # the terms that are not modules
        self._keys: dict[str, str] = {}           # term name -> its key in self.terms
        entries = []
        for name, entry in terms.items():
            if not (isinstance(entry, (tuple, list)) and len(entry) == 2 and callable(entry[1])):
                raise TypeError(f"terms[{name!r}]: expected (weight, callable term), got {entry!r}")
            weight, term = entry
            if isinstance(weight, Tensor) and weight.requires_grad:  # (read as a float: its gradient lost)
                raise TypeError(f"terms[{name!r}] weight: expected a fixed number, got a tensor that requires grad "
                                f"(the weights are constants, and the values reported are detached: to learn a "
                                f"weight, call the terms yourself and weight their values)")
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

    def extra_repr(self) -> str:
        # (the weights, and the terms that are functions, not submodules: else not shown)
        functions = ", ".join(f"{k!r}: {getattr(f, '__qualname__', f)!s}" for k, f in self._functions.items())
        return f"weights={self.weights!r}" + (f", functions={{{functions}}}" if functions else "")

    def _term(self, name: str):
        return self.terms[self._keys[name]] if name in self._keys else self._functions[name]

    def forward(self, flows: Tensor | Sequence[Tensor], inputs: Mapping[str, object] | None = None,
                **more: object) -> tuple[Tensor, dict[str, Tensor]]:
        """``(total, {name: value})`` of the terms on ``flows`` and the named inputs (see the class)."""
        if inputs is not None and not isinstance(inputs, Mapping):
            raise TypeError(f"inputs: expected None or a mapping of named inputs (a batch dict), "
                            f"got {type(inputs).__name__}")
        given = {**(inputs or {}), **more}
        total = 0.0
        values: dict[str, Tensor] = {}
        for name, weight in self.weights.items():
            accepted, takes_all, bound = self._names[name]
            kwargs = ({k: v for k, v in given.items() if k not in bound} if takes_all else
                      {k: v for k, v in given.items() if k in accepted})
            try:
                value = self._term(name)(flows, **kwargs)
            except TypeError as exc:
                raise TypeError(f"terms[{name!r}]: {exc} (inputs given: {sorted(map(str, given))})") from exc
            value = value if isinstance(value, Tensor) else torch.as_tensor(value, device="cpu")
            if value.numel() != 1:  # ((B,) would broadcast against the scalar terms: each added B times by a sum)
                raise ValueError(f"terms[{name!r}]: expected a scalar loss, got shape {tuple(value.shape)} (a term "
                                 f"built with reduction='none'? CompositeLoss adds scalars: 'mean' or 'sum')")
            values[name] = value.detach()
            if weight:  # a weight-0 term is only reported: 0 * inf would make the total NaN
                total = total + weight * value
        if not isinstance(total, Tensor):  # every weight 0: nothing reaches the flows
            dtype = value.dtype if value.is_floating_point() else torch.get_default_dtype()
            total = torch.zeros((), dtype=dtype, device=value.device, requires_grad=torch.is_grad_enabled())
        elif torch.is_grad_enabled() and not total.requires_grad:
            # the weighted terms carry no gradient (Python numbers): a total that backward() still
            # accepts, as with every weight 0
            total = total + torch.zeros((), dtype=total.dtype, device=total.device, requires_grad=True)
        return total, values


def _module_key(name: object, probe: nn.ModuleDict) -> bool:
    """Whether ``name`` can key a submodule of ``probe`` (an empty ``nn.ModuleDict``)."""
    return isinstance(name, str) and name != "" and "." not in name and not hasattr(probe, name)


def _accepted_names(term: object) -> tuple[set[str], bool, frozenset[str]]:
    """Keyword names ``term`` accepts after ``flows``, whether it takes ``**kwargs``, and the
    keywords a ``functools.partial`` binds (never fed: a call's keyword would override them)."""
    bound = frozenset()
    if isinstance(term, functools.partial):
        # (the signature of a partial lists its bound keywords as parameters with those defaults;
        # a partial of a module: its forward's, with what the partial binds)
        bound = frozenset(term.keywords)
        inner = _compiled_module(term.func)
        fn = functools.partial(inner.forward, *term.args, **term.keywords) if isinstance(inner, nn.Module) else term
    else:
        term = _compiled_module(term)
        fn = term.forward if isinstance(term, nn.Module) else term
    try:
        params = list(inspect.signature(fn).parameters.values())[1:]
    except ValueError:  # no signature Python can read
        schema = getattr(fn, "schema", None)
        if schema is not None:  # a torch.jit.trace'd module's forward: its TorchScript schema (self, flows, ...)
            return {a.name for a in schema.arguments[2:]} - bound, False, bound
        params = []  # a builtin (torch.mean): it is fed the flows alone
    takes_all = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
    names = {p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                   inspect.Parameter.KEYWORD_ONLY)} - bound
    return names, takes_all, bound


def _compiled_module(term: object) -> object:
    """The module a ``torch.compile(module)`` wraps (its wrapper's forward takes (*args, **kwargs):
    reading it, the term would be fed every input and refuse the others); ``term`` otherwise."""
    while isinstance(term, nn.Module) and isinstance(getattr(term, "_orig_mod", None), nn.Module):
        term = term._orig_mod
    return term
