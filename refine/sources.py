"""Flow sources of the job: OpenCV DIS, the test net (random weights unless a state_dict is
given), flow files written by any network, or a user's network (``--net module:callable``).

Every source is built, and its weights loaded, before the first pair is processed, so a bad
``--testnet-weights``, ``--net`` or ``--checkpoint`` stops the job before any work.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor, nn

from .inputs import JobError

SOURCES = ("dis", "testnet", "net")
CONTRACTS = ("auto", "ptlflow", "torchvision", "raft")


def dis_flow(image1: Tensor, image2: Tensor, *, preset: str = "medium") -> Tensor:
    """OpenCV DIS optical flow (``PRESET_MEDIUM`` by default) on grey images.

    Args:
        image1, image2: (3, H, W) float 0..255 RGB.

    Returns:
        (2, H, W) float32 forward flow in pixels.
    """
    import cv2
    import numpy as np

    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}

    def grey(image: Tensor) -> "np.ndarray":
        rgb = image.detach().to(torch.float32).clamp(0, 255).permute(1, 2, 0).cpu().numpy()
        return cv2.cvtColor(rgb.round().astype(np.uint8), cv2.COLOR_RGB2GRAY)

    dis = cv2.DISOpticalFlow_create(presets[preset])
    flow = dis.calc(grey(image1), grey(image2), None)
    return torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1))).to(torch.float32)


@dataclass
class NetSpec:
    """A user's network: ``factory`` as ``module:callable``, the contract it follows, an optional
    local checkpoint (a state_dict)."""

    factory: str
    contract: str = "auto"
    checkpoint: Path | None = None


#: keys under which a training checkpoint keeps the network's state_dict (:func:`load_state_dict`)
WRAPPER_KEYS = ("state_dict", "model", "model_state_dict")
#: prefixes that wrappers add to every name of a network's state_dict, removed by
#: :func:`load_state_dict` where the network's own names lack them: ``nn.DataParallel`` and
#: ``DistributedDataParallel``'s, and that of a ``torch.compile``'d network
WRAPPER_PREFIXES = ("module.", "_orig_mod.")


def load_state_dict(net: nn.Module, path: Path, option: str) -> None:
    """Load a local state_dict (``torch.load(weights_only=True)``: tensors only, no code) into
    ``net``; every problem is a JobError naming ``option`` and the file."""
    if path.is_dir():
        raise JobError(f"{option}: {str(path)!r} is a folder; expected a file (a state_dict saved by torch.save)")
    if not path.is_file():
        raise JobError(f"{option}: no file at {str(path)!r}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load raises many types on foreign bytes (pickle, zip, EOF)
        raise JobError(_load_failure(err, path, option)) from None
    # a training checkpoint keeps the weights under one key beside others (the optimiser's state,
    # the step): Lightning's and ptlflow's "state_dict", "model" (GMFlow, FlowFormer, ...),
    # "model_state_dict" (PyTorch's tutorial). A state_dict's own values are tensors, never dicts.
    wrapper = next((k for k in WRAPPER_KEYS if isinstance(state, dict) and isinstance(state.get(k), dict)), None)
    if wrapper is not None:
        state = state[wrapper]
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise JobError(f"{option}: {str(path)!r} holds a {type(state).__name__}, not a state_dict "
                       f"(a dict of parameter names to tensors)")
    own = set(net.state_dict())
    while state and set(state) != own:
        # the weights of a network saved inside a wrapper, whose name starts every name and which
        # the bare network's names lack: nn.DataParallel's (RAFT's released checkpoints) or
        # DistributedDataParallel's "module.", torch.compile's "_orig_mod." (either inside the other)
        prefix = next((p for p in WRAPPER_PREFIXES if all(k.startswith(p) for k in state)), None)
        if prefix is None:
            break
        from torch.nn.modules.utils import consume_prefix_in_state_dict_if_present

        consume_prefix_in_state_dict_if_present(state, prefix)  # (in place, on the dict just loaded)
    state = _attribute_stripped(state, own)
    try:
        # a network built on the meta device (shapes only, to be filled from a checkpoint) takes
        # the file's tensors themselves: copying into its meta tensors would keep no value
        result = net.load_state_dict(state, strict=True, assign=bool(_meta_tensors(net)))
    except RuntimeError as err:
        own = set(net.state_dict())
        missing, unexpected = sorted(own - set(state)), sorted(set(state) - own)
        detail = (f"missing keys {_first_keys(missing)}, unexpected keys {_first_keys(unexpected)}"
                  if missing or unexpected else str(err).splitlines()[-1].strip())
        raise JobError(f"{option}: {str(path)!r} does not fit {type(net).__name__}: {detail}") from None
    del result


def _attribute_stripped(state: dict, own: set[str]) -> dict:
    """``state`` with the attribute name that starts every one of its names removed, where the
    names left are exactly the network's own: the weights of a network kept as an attribute of
    the module that trained it (a Lightning module's ``self.model``, ``self.net``: ``model.fnet.``
    ...). Otherwise ``state`` as it came (a name of its own is never guessed away)."""
    firsts = {k.partition(".")[0] for k in state}
    if not state or set(state) == own or len(firsts) != 1 or not all("." in k for k in state):
        return state
    prefix = f"{firsts.pop()}."
    stripped = {k[len(prefix):]: v for k, v in state.items()}
    return stripped if set(stripped) == own else state


def _first_keys(keys: list[str], shown: int = 4) -> str:
    """The first ``shown`` of ``keys`` and how many more there are (a checkpoint of another
    architecture misses hundreds: four shown alone read as four)."""
    more = f" and {len(keys) - shown} more" if len(keys) > shown else ""
    return f"{keys[:shown]}{more}"


def _meta_tensors(net: nn.Module) -> list[str]:
    """The names of ``net``'s parameters and buffers on the meta device (shapes, no values)."""
    return [name for name, t in (*net.named_parameters(), *net.named_buffers()) if t.is_meta]


def _load_failure(err: Exception, path: Path, option: str) -> str:
    """The message for a file ``torch.load(weights_only=True)`` refused: torch's own first line
    ("Weights only load failed. ... Re-running `torch.load` with `weights_only` set to `False`
    will likely succeed", with terminal colour codes) suggested what the job never does, said so
    of bytes that are no checkpoint at all, and left out the reason; the reason is in its
    ``WeightsUnpickler error:`` part (an object the file pickles, or the byte it stopped at)."""
    import re

    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err))
    _, found, rest = text.partition("WeightsUnpickler error:")
    detail = rest.strip().splitlines()[0].strip() if found and rest.strip() else \
        (text.splitlines()[0] if text else "")
    pickled = re.match(r"Unsupported global: GLOBAL (\S+)", detail)
    if pickled:  # a whole network, or a training checkpoint's objects beside its weights
        return (f"{option}: {str(path)!r} holds a pickled {pickled.group(1)}, not only tensors; the job loads "
                f"tensors alone (torch.load(weights_only=True): a checkpoint cannot run code): save the weights "
                f"once as a state_dict from a file you trust, e.g. torch.save(model.state_dict(), ...) or "
                f"torch.save(checkpoint['state_dict'], ...) (docs/contracts.md)")
    return (f"{option}: {str(path)!r} is not a state_dict file torch.load(weights_only=True) can read "
            f"({type(err).__name__}: {detail})")


def build_user_net(spec: NetSpec) -> tuple[nn.Module, str, bool]:
    """Import ``module:callable`` (its files as they are now: :func:`forget_user_code`), call it,
    check what it returns; load the checkpoint. Returns the network in eval mode, the contract it
    follows, and whether that contract was guessed from its one-argument forward alone
    (:func:`_contract`)."""
    module_name, sep, attr = spec.factory.partition(":")
    if not sep or not module_name or not attr:
        raise JobError(f"--net: expected module:callable such as mypkg.models:make_raft, got {spec.factory!r}")
    forget_user_code(spec.factory)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        raise JobError(_file_path_name(module_name, attr) or f"--net: cannot import module {module_name!r} ({err}); "
                       f"is it installed, or on PYTHONPATH?") from None
    except Exception as err:  # the user's module failed while importing (or ./nets.py: a relative name)
        relative = _file_path_name(module_name, attr) if module_name.startswith(".") else None
        raise JobError(relative or f"--net: importing {module_name!r} failed: {type(err).__name__}: {err}") from None
    except SystemExit as err:  # (research code that parses the command line, or exits, when imported)
        raise JobError(f"--net: importing {module_name!r} exited (SystemExit: {err.code!r}); the job imports the "
                       f"module and calls its factory: it may not parse the command line or exit") from None
    factory: Any = module
    for part in attr.split("."):
        if not hasattr(factory, part):
            raise JobError(f"--net: module {module_name!r} has no attribute {attr!r}")
        factory = getattr(factory, part)
    if isinstance(factory, nn.Module):
        # the network itself (calling it would run its forward without images): named as its class
        raise JobError(f"--net: {spec.factory!r} is a network (a {type(factory).__name__}), not a factory; name a "
                       f"function or class that returns it, e.g. {module_name}:{type(factory).__name__}")
    if not callable(factory):
        raise JobError(f"--net: {spec.factory!r} is a {type(factory).__name__}, not a callable")
    try:
        net = factory()
    except Exception as err:
        raise JobError(f"--net: calling {spec.factory}() failed: {type(err).__name__}: {err}") from None
    except SystemExit as err:
        raise JobError(f"--net: calling {spec.factory}() exited (SystemExit: {err.code!r})") from None
    if not isinstance(net, nn.Module):
        raise JobError(f"--net: {spec.factory}() returned a {type(net).__name__}; expected a torch.nn.Module")
    if spec.checkpoint is not None:  # (into the network a wrapper holds: a checkpoint of the bare network fits)
        load_state_dict(_wrapped_network(net), spec.checkpoint, "--checkpoint")
    meta = _meta_tensors(net)
    if meta:  # (moving it to --device would fail on them, and a forward give no values)
        more = f" and {len(meta) - 1} more" if len(meta) > 1 else ""
        raise JobError(f"--net: {spec.factory}() returned a network whose {meta[0]!r}{more} on the device 'meta' "
                       f"hold no values (shapes only); " + ("give them in --checkpoint" if spec.checkpoint is None
                                                             else "--checkpoint does not give them"))
    net.eval()
    return (net, *_contract(net, spec))


def _file_path_name(module_name: str, attr: str) -> str | None:
    """The message for ``--net``'s module given as a file path (``nets/raft.py``), which no import
    finds: the dotted name to give instead and the folder to put on PYTHONPATH; None for a name."""
    if not any(c in module_name for c in "/\\") and not module_name.endswith(".py"):
        return None
    path = Path(module_name.replace("\\", "/").removesuffix(".py"))
    dotted, folder = ((path.name, str(path.parent)) if path.is_absolute() or ".." in path.parts
                      else (".".join(path.parts), "."))
    return (f"--net: {module_name!r} is a file path, not a module name; give the module's dotted name with the "
            f"folder it is found from on PYTHONPATH, e.g. --net {dotted}:{attr} with PYTHONPATH={folder}")


def _contract(net: nn.Module, spec: NetSpec) -> tuple[str, bool]:
    """The contract a network follows: the option's, else the class's ``flow_contract``
    attribute, else its package (ptlflow, torchvision), else a one-argument forward (ptlflow's);
    and whether it was guessed from that forward alone."""
    if spec.contract != "auto":
        return spec.contract, False
    net = _wrapped_network(net)  # (a wrapper's forward takes *args: the contract is its network's)
    declared = getattr(net, "flow_contract", None)
    if declared in CONTRACTS[1:]:
        return declared, False
    if declared is not None:  # (a misspelt contract would otherwise be guessed from the forward)
        raise JobError(f"--net-contract: {type(net).__name__}.flow_contract is {declared!r}; expected one of "
                       f"{', '.join(CONTRACTS[1:])} (or give --net-contract)")
    package = type(net).__module__.split(".")[0]
    if package in ("ptlflow", "torchvision"):
        return package, False
    try:
        params = [p for p in inspect.signature(net.forward).parameters.values()
                  if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]
    except (TypeError, ValueError):
        params = []
    if len(params) == 1:
        return "ptlflow", True
    raise JobError(f"--net-contract: cannot tell how to call {type(net).__name__} (forward takes "
                   f"{len(params)} image arguments); give ptlflow, torchvision (RGB in [-1, 1]) or raft (RGB 0..255)")


def _wrapped_network(net: nn.Module) -> nn.Module:
    """The network inside the wrappers a factory may return (RAFT's demo builds
    ``nn.DataParallel(RAFT(args))``): ``nn.DataParallel``'s and ``DistributedDataParallel``'s
    ``module``, a ``torch.compile``'d network's ``_orig_mod``; ``net`` itself otherwise."""
    while True:
        if isinstance(net, (nn.DataParallel, nn.parallel.DistributedDataParallel)):
            net = net.module
        elif type(net).__name__ == "OptimizedModule" and type(net).__module__.startswith("torch."):
            net = net._orig_mod
        else:
            return net


def net_flow(net: Callable[..., Any], contract: str, image1: Tensor, image2: Tensor, *,
             option: str = "--net", hint: str = "") -> Tensor:
    """Run a network of the given contract on one pair ((3, H, W) RGB 0..255) and return its
    final full-size flow (2, H, W) float32. Sizes are padded as RAFT does when the contract
    needs it (torchvision, raft: to a multiple of 8) and the output cropped back.

    The network gets copies of the images (one that normalises its inputs in place leaves the
    pair as it was), in the dtype of its first floating parameter where it has one. A forward that
    raises (its message ends with ``hint``), and an output that holds no flow, are JobErrors
    naming ``option``.
    """
    from fsof_torch.refinement.contracts import (DEFAULT_FLOW_KEYS, InputPadder, collect_flows, finest_flow,
                                                 ptlflow_inputs)

    dtype = next((p.dtype for p in net.parameters() if p.is_floating_point()), torch.float32) \
        if isinstance(net, nn.Module) else torch.float32
    im1, im2 = image1[None].to(dtype, copy=True), image2[None].to(dtype, copy=True)
    size = tuple(im1.shape[-2:])
    padding = InputPadder(8).padding(size)
    # (built before the network runs: a failure here is the images', not the network's)
    inputs = ptlflow_inputs(im1, im2) if contract == "ptlflow" else None
    with torch.no_grad():
        try:
            if contract == "ptlflow":
                output = net(inputs)  # ptlflow's models pad internally
            else:
                if contract == "torchvision":
                    im1, im2 = im1 / 127.5 - 1.0, im2 / 127.5 - 1.0
                output = net(padding.pad(im1), padding.pad(im2))
        except (Exception, SystemExit) as err:  # the user's code: any type, or sys.exit()
            padded = "" if contract == "ptlflow" or padding.is_zero else (
                f"; the job padded the images from {size[0]}x{size[1]} to "
                f"{'x'.join(map(str, padding.padded_size(size)))}, a multiple of 8")
            raise JobError(f"{option}: the network raised {type(err).__name__}: "
                           f"{str(err).splitlines()[0] if str(err) else ''} (contract {contract}{padded}){hint}") \
                from None
        try:
            if contract != "ptlflow":
                output = padding.unpad_output(output, padding.padded_size(size))
            flows = collect_flows(output, "output")
        except (TypeError, ValueError) as err:
            raise JobError(f"{option}: {err}") from None
    if not flows:
        raise JobError(f"{option}: its output holds no flow (a {type(output).__name__}; a dict needs one of the "
                       f"keys {', '.join(DEFAULT_FLOW_KEYS[:3])}, ...)")
    _, flow = finest_flow(flows)
    if tuple(flow.shape[-2:]) != size:
        raise JobError(f"{option}: the network's finest flow is {tuple(flow.shape[-2:])}, the images {size}")
    if flow.shape[0] != 1:  # (the job gives one pair at a time: which flow is the pair's is unknown)
        raise JobError(f"{option}: the network's finest flow has batch {flow.shape[0]} (shape {tuple(flow.shape)}), "
                       f"the images 1 (one pair)")
    if flow.device.type == "meta":  # (no values to refine: every later step would fail on it)
        raise JobError(f"{option}: the network returned its flow on the device 'meta' (shapes only, no values), "
                       f"the images on {str(image1.device)!r}")
    return flow[0].to(torch.float32)


def make_source(name: str, *, weights: Path | None = None, net: NetSpec | None = None,
                device: torch.device | str = "cpu") -> Callable[[dict, Path | None], Tensor]:
    """A callable ``(pair, flow_file) -> flow (2, H, W)`` for source ``name`` (built now: weights
    and networks load here); networks run on ``device``."""
    if name == "dis":
        return lambda pair, _file: dis_flow(pair["image1"], pair["image2"])
    if name == "testnet":
        from fsof_torch import TinyRAFT

        testnet = TinyRAFT(seed=0)
        if weights is not None:
            load_state_dict(testnet, weights, "--testnet-weights")
        testnet.eval().to(device)
        # the job keeps the last flow only: the iterations before it are not upsampled
        final = functools.partial(testnet, final_only=True)
        return lambda pair, _file: net_flow(final, "raft", pair["image1"], pair["image2"],
                                            option="--source testnet")
    if name == "net":
        if net is None:
            raise JobError("--source net needs --net module:callable")
        model, contract, guessed = build_user_net(net)
        model.to(device)
        hint = ("; the contract was guessed from its one-argument forward: give --net-contract, or call "
                "a network of another input (ARFlow's pair concatenated) through an adapter (docs/contracts.md)"
                if guessed else "")
        return lambda pair, _file: net_flow(model, contract, pair["image1"], pair["image2"], hint=hint)
    if name == "files":
        from fsof_torch import read_flow

        def read(pair: dict, file: Path | None) -> Tensor:
            if file is None:
                raise JobError("--flows: no flow file for this pair")
            try:
                flow, valid = read_flow(file)
            except (ValueError, FileNotFoundError) as err:  # a reader's message names its argument: path
                raise JobError(f"--flows: {str(err).removeprefix('path: ')}") from None
            size = tuple(pair["image1"].shape[-2:])
            if tuple(flow.shape[-2:]) != size:
                raise JobError(f"--flows: {file.name} is {tuple(flow.shape[-2:])}, the images {size}")
            # invalid pixels of a flow file carry no prediction: NaN keeps them out of the fit
            return torch.where(valid, flow, torch.full_like(flow, float("nan")))
        return read
    raise JobError(f"--source: unknown flow source {name!r}; choose from {', '.join(SOURCES)} or give --flows")


def net_module_file(factory: str) -> Path | None:
    """The source file of the module of ``factory`` (``module:callable``), None where it has none
    (a built-in or namespace module) or cannot be found."""
    try:
        found = importlib.util.find_spec(factory.partition(":")[0])
    except (Exception, SystemExit):  # (finding a submodule imports its package, whose code may raise
        return None                  # anything or exit: build_user_net imports it again, names it)
    if found is not None and found.origin and Path(found.origin).is_file():
        return Path(found.origin)
    return None


def forget_user_code(factory: str) -> None:
    """Drop the modules of the user's code that an earlier import of ``factory``'s module loaded
    (its module and :func:`user_code_files`) from ``sys.modules``, so that importing it again reads
    their files as they are now: ``main()`` called again in one process ran the network of the
    first call's files while the identity held the digests of the files as edited since."""
    import sys

    for name in user_code_files(factory, own=True):
        sys.modules.pop(name, None)
    importlib.invalidate_caches()


def user_code_files(factory: str, *, own: bool = False) -> dict[str, Path]:
    """The files of the user's code that importing ``factory``'s module and calling it loaded, by
    module name: every module in ``sys.modules`` (nothing is imported here) whose file lies in the
    folder of the factory's top-level package (each folder of a namespace package) or, for a
    top-level module, in the folder that holds it. Files in the standard library, in a
    site-packages or dist-packages folder, in an interpreter's prefix inside that folder (a
    virtual environment in the project) or in the job's own packages (fsof_torch, refine) are
    left out, and so is every file of a top-level package or module that lies in one of those
    (an installed package: the environment's, not the user's project). The factory's own module
    (:func:`net_module_file`; kept with ``own``) and the script that runs the job (``__main__``)
    are left out too."""
    import os
    import site
    import sys
    import sysconfig

    import fsof_torch

    module_name = factory.partition(":")[0]
    top = sys.modules.get(module_name.split(".")[0])
    spec = getattr(top, "__spec__", None)
    folders = list(getattr(spec, "submodule_search_locations", None) or [])  # a package's folder(s)
    if not folders and isinstance(getattr(top, "__file__", None), str):
        folders = [os.path.dirname(top.__file__)]  # a top-level module: the folder beside it
    library = {sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    library |= {*site.getsitepackages(), site.getusersitepackages()}
    job = {os.path.dirname(fsof_torch.__file__), os.path.dirname(__file__)}
    prefixes = {sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix}

    def under(path: str, folder: str) -> bool:
        return any(Path(f(path)).is_relative_to(f(folder)) for f in (os.path.abspath, os.path.realpath))

    def environment(path: str) -> bool:
        return (any(under(path, d) for d in library | job)
                or bool({"site-packages", "dist-packages"} & set(Path(os.path.abspath(path)).parts)))

    roots = [r for r in map(os.path.abspath, folders) if not environment(r)]
    inner = [p for p in prefixes if any(under(p, r) and not under(r, p) for r in roots)]
    found = {}
    for name, module in list(sys.modules.items()):
        file = getattr(module, "__file__", None)
        if (name in ("__main__", "__mp_main__") or (name == module_name and not own) or not isinstance(file, str)
                or not os.path.isfile(file)):
            continue
        if any(under(file, r) for r in roots) and not environment(file) and not any(under(file, p) for p in inner):
            found[name] = Path(file)
    return found


def net_identity(spec: NetSpec | None) -> dict[str, Any] | None:
    """What identifies a user's network for resuming: the factory, the contract, the checkpoint's
    contents, the source file of the factory's module and, under ``code`` (only where there are
    any), the contents of the other files of the user's code its import and call loaded
    (:func:`user_code_files`), by module name. Call it after :func:`build_user_net`."""
    if spec is None:
        return None
    from .inputs import file_digest

    source = net_module_file(spec.factory)
    module_file = file_digest(source) if source is not None else None
    identity = {"factory": spec.factory, "contract": spec.contract, "module_file": module_file,
                "checkpoint": file_digest(spec.checkpoint) if spec.checkpoint is not None and spec.checkpoint.is_file()
                else None}
    code = {name: file_digest(path) for name, path in sorted(user_code_files(spec.factory).items())}
    if code:  # (a network in one module keeps the identity it had)
        identity["code"] = code
    return identity
