"""The documentation tells the truth to a user who copies from it: every internal link reaches a
file and a heading, the indexes list every page, every Python example of docs/*.md runs
(fragments with the inputs their page says the user has, and the imports the page itself gives),
the signatures and calls the pages write out are the code's, every `fsof_torch.x` they name
exists, the options tables name the options with their defaults, docs/jobs.md lists exactly the
jobs' options, and every command the pages give names a script and options that exist."""

import argparse
import ast
import contextlib
import functools
import importlib
import inspect
import io
import re
import sys
import types
import unicodedata
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
FENCE = re.compile(r"^([ \t]*)```(\w*)\n(.*?)^\1```", re.S | re.M)


def _without_fences(text: str) -> str:
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped (not - or _), spaces to hyphens,
    a repeated heading numbered -1, -2, ..."""
    out, seen = set(), {}
    for m in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", _without_fences(page.read_text()), re.M):
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", m.group(1)).replace("`", "").replace("*", "")
        anchor = "".join(c for c in text.strip().lower()
                         if c in " -_" or unicodedata.category(c)[0] in "LN").replace(" ", "-")
        n = seen.get(anchor, 0)
        seen[anchor] = n + 1
        out.add(anchor if n == 0 else f"{anchor}-{n}")
    return out


def test_the_anchor_rule_is_githubs():
    assert _anchors(DOCS / "jobs.md") >= {"python--m-refine", "resuming-and-fingerprints", "long-clips"}
    assert "why-l1-alone-misleads-and-what-to-report-beside-it" in _anchors(DOCS / "evaluation.md")


def test_internal_links_reach_a_file_and_a_heading():
    broken = []
    for page in PAGES:
        text = _without_fences(page.read_text())
        for m in re.finditer(r"\]\(([^)\s]+)\)", text):
            target = m.group(1)
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            line = text[:m.start()].count("\n") + 1
            if not file.exists():
                broken.append(f"{page.name}:{line}: no file {target}")
            elif anchor and anchor not in _anchors(file):
                broken.append(f"{page.name}:{line}: no heading #{anchor} in {file.name}")
    assert not broken, broken


def test_the_index_lists_every_page():
    """docs/README.md links every page of docs/ (and the README's Documentation list does too)."""
    index = set(re.findall(r"\]\(([\w-]+\.md)\)", (DOCS / "README.md").read_text()))
    pages = {p.name for p in DOCS.glob("*.md")} - {"README.md"}
    assert index == pages
    text = (ROOT / "README.md").read_text()
    listed = set(re.findall(r"\]\(docs/([\w-]+\.md)[#)]", text[text.index("## Documentation"):]))
    assert listed == pages | {"README.md"}


# -- the Python examples -----------------------------------------------------------------------

# What each page's text says the user already has, at a small size so that the examples run fast.
PRELUDE = """
import torch, fsof_torch, fsof_torch as fs
pair = fs.render_pair("default", 0, size=SIZE)
image1, image2 = pair["image1"][None], pair["image2"][None]
frame1, frame2, rgb1, rgb2 = image1, image2, image1, image2
road = mask = pair["road"][None]
valid = flow_valid = pair["valid"][None]
camera, odometry = pair["camera"], pair["odometry"]
flow_gt = pair["flow"][None]
flow = flow_est = flow_gt + torch.randn(flow_gt.shape, generator=torch.Generator().manual_seed(0))
"""

# the size of the user's data: the page's own where its examples render a pair for the fragments after
PAGE_SIZE = {"refinement.md": (188, 621)}

PAGE_PRELUDE = {
    # a Lightning checkpoint of the ptlflow stand-in, for the extraction example
    "contracts.md": """
from fsof_torch.training.standins import ptlflow_raft
torch.save({"state_dict": ptlflow_raft().state_dict(), "epoch": 1}, "raft-things.ckpt")
class _PWCLite(torch.nn.Module):  # ARFlow's call: model(torch.cat([image1, image2], 1)) on 0..1
    def __init__(self):
        super().__init__()
        self.raft = fs.TinyRAFT(seed=0, iters=2)

    def forward(self, x, with_bk=False):
        assert x.shape[1] == 6 and x.shape[-2] % 64 == x.shape[-1] % 64 == 0 and 0 <= x.min() <= x.max() <= 1
        f = self.raft(x[:, :3] * 255, x[:, 3:] * 255)[-1]
        return {"flows_fw": [f, torch.nn.functional.avg_pool2d(f, 2) / 2]}
arflow = _PWCLite()
""",
    "data-formats.md": """
open("lanes.json", "w").write("[[[0, 374], [300, 250], [500, 374]], [[700, 374], [800, 260], [1000, 374]]]")
""",
    "evaluation.md": """
loader = [{"flow_est": flow, "flow_gt": flow_gt, "road": road, "valid": valid}] * 2
""",
    "fitting.md": """
fs.io.write_kitti_calibration("calib_cam_to_cam.txt", camera.K[0])
""",
    "image-fit.md": """
paths = []
for k, p in enumerate(fs.render_sequence("default", 2, size=(96, 320))):
    paths.append(f"{k:06d}.png")
    fs.write_image(paths[-1], p["image1"])
paths.append("000002.png")
fs.write_image(paths[-1], p["image2"])
""",
    # a KITTI flow 2015 training folder of one pair (the synthetic pair), for the loop over a data set
    "refinement.md": """
import os
for sub in ("image_2", "flow_noc", "calib_cam_to_cam"):
    os.makedirs(f"data_scene_flow/training/{sub}")
fs.write_image("data_scene_flow/training/image_2/000000_10.png", pair["image1"])
fs.write_image("data_scene_flow/training/image_2/000000_11.png", pair["image2"])
fs.write_flow("data_scene_flow/training/flow_noc/000000_10.png", pair["flow"], pair["valid"])
fs.io.write_kitti_calibration("data_scene_flow/training/calib_cam_to_cam/000000.txt", camera.K[0])
""",
    "training.md": """
from eval.__main__ import main as eval_main
assert eval_main(["synth", "--preset", "default", "--pairs", "4", "--out", "runs/synth", "--size", "64", "224",
                  "--no-progress"]) == 0
""",
}

# (page, block index): why the block cannot run here
SKIP = {
    ("refinement.md", 3): "its last line calls a ptlflow network (contracts.md's example runs one: the stand-in)",
}


def _fake_external_packages(monkeypatch):
    """ptlflow and torchvision as the examples use them, backed by the library's stand-ins."""
    from fsof_torch.training import standins

    ptlflow = types.ModuleType("ptlflow")
    ptlflow.get_model = lambda name: standins.ptlflow_raft()
    def optical_flow_transforms(image1, image2):
        """torchvision's OpticalFlow preset: convert_image_dtype (uint8 to [0, 1], a float kept
        as it is), then normalize by mean 0.5, std 0.5."""
        return tuple((x / 255 if x.dtype == torch.uint8 else x) * 2 - 1 for x in (image1, image2))

    weights = types.SimpleNamespace(transforms=lambda: optical_flow_transforms)
    optical_flow = types.ModuleType("torchvision.models.optical_flow")
    optical_flow.Raft_Large_Weights = types.SimpleNamespace(DEFAULT=weights)
    optical_flow.raft_large = lambda weights=None: standins.torchvision_raft()
    models = types.ModuleType("torchvision.models")
    models.optical_flow = optical_flow
    torchvision = types.ModuleType("torchvision")
    torchvision.models = models
    for name, module in (("ptlflow", ptlflow), ("torchvision", torchvision), ("torchvision.models", models),
                         ("torchvision.models.optical_flow", optical_flow)):
        monkeypatch.setitem(sys.modules, name, module)


def _python_blocks(page: Path) -> list[tuple[int, str]]:
    import textwrap

    text = page.read_text()
    return [(text[:m.start()].count("\n") + 1, textwrap.dedent(m.group(3)))
            for m in FENCE.finditer(text) if m.group(2) == "python"]


def _runs(code: str) -> bool:
    try:
        compile(code, "<block>", "exec")
    except SyntaxError:
        return False
    return True


EXAMPLE_PAGES = [p.name for p in sorted(DOCS.glob("*.md")) if any(_runs(c) for _, c in _python_blocks(p))]


@pytest.mark.parametrize("name", EXAMPLE_PAGES)
def test_the_python_examples_of_a_page_run(name, tmp_path, monkeypatch):
    """Each page's Python blocks in order, in one namespace (a fragment sees the blocks before it),
    from an empty folder, with the inputs the page's text gives the user."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(ROOT))
    _fake_external_packages(monkeypatch)
    torch.manual_seed(0)
    namespace = {"__name__": "__main__"}
    namespace["SIZE"] = PAGE_SIZE.get(name, (96, 320))
    exec(PRELUDE + PAGE_PRELUDE.get(name, ""), namespace)
    for module in ("torch", "fsof_torch", "fs"):  # the user's data, not the prelude's imports:
        del namespace[module]                      # a page imports what its examples use
    ran = 0
    for index, (line, code) in enumerate(_python_blocks(DOCS / name)):
        if (name, index) in SKIP or not _runs(code):
            continue
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                exec(compile(code, f"{name}:{line}", "exec"), namespace)
        except Exception as error:  # noqa: BLE001 - the report names the block
            raise AssertionError(f"docs/{name}, the block at line {line}: {type(error).__name__}: {error}") from error
        ran += 1
    assert ran


# -- signatures written out --------------------------------------------------------------------

@functools.cache
def _library_modules():
    import pkgutil

    import fsof_torch

    return [fsof_torch] + [importlib.import_module(m.name)
                           for m in pkgutil.walk_packages(fsof_torch.__path__, "fsof_torch.")]


def _resolve(name: str):
    """The callable a page's name stands for: an attribute path from the package or from any of
    its modules (``fit_image``, ``Camera.padded``, ``camera.scaled`` a Camera's method,
    ``ImageFolderDataset``), None where no module or several different objects answer to it."""
    parts = name.split(".")
    if parts[0] in ("fs", "fsof_torch"):
        parts = parts[1:]
    if parts and parts[0] == "camera" and len(parts) > 1:
        parts[0] = "Camera"
    found = []
    for module in _library_modules():
        obj = module
        for part in parts:
            obj = getattr(obj, part, None)
            if obj is None:
                break
        if obj is not None and callable(obj) and not any(obj is f for f in found):
            found.append(obj)
    return found[0] if len(found) == 1 else None


def _written_signatures():
    """Signatures the pages write out: a Python block that is not code, or an inline span, of the
    form ``name(params)`` with a bare ``*`` or ``**name`` among the params."""
    for page in PAGES:
        text = page.read_text()
        spans = [code for _, code in _python_blocks(page) if not _runs(code)]
        spans += re.findall(r"`([^`]+)`", _without_fences(text))
        for span in spans:
            m = re.fullmatch(r"\s*([A-Za-z_][\w.]*)\((.*)\)\s*", span, re.S)
            if not m or not re.search(r"(^|,)\s*\*\*?\w*\s*(,|$)", m.group(2)):
                continue
            obj = _resolve(m.group(1))
            if obj is None or not callable(obj):
                continue
            yield page.name, m.group(1), m.group(2), obj


def _parse_params(params: str):
    """(name, kind, default or ..., has_default) of each written parameter; `...` marks a partial list."""
    partial = "..." in params or "…" in params
    params = re.sub(r",?\s*(\.\.\.|…)", "", params)
    params = re.sub(r"=\s*(?=,|$)", "=_unwritten", params.replace("\\|", "|"))
    tree = ast.parse(f"def f({params}): pass").body[0].args
    out = []
    positional = tree.posonlyargs + tree.args
    defaults = [None] * (len(positional) - len(tree.defaults)) + list(tree.defaults)
    for arg, default in zip(positional, defaults):
        out.append((arg.arg, "positional", default))
    for arg, default in zip(tree.kwonlyargs, tree.kw_defaults):
        out.append((arg.arg, "keyword", default))
    if tree.vararg:
        out.append((tree.vararg.arg, "var", None))
    if tree.kwarg:
        out.append((tree.kwarg.arg, "varkw", None))
    return out, partial


def test_written_signatures_are_the_codes():
    found, wrong = 0, []
    for page, name, params, obj in _written_signatures():
        found += 1
        code = inspect.signature(obj).parameters
        code = {k: v for k, v in code.items() if k != "self"}
        written, partial = _parse_params(params)
        starred = bool(re.search(r"(^|,)\s*\*\s*(,|$)", params))
        partial = partial or all(kind == "varkw" for _, kind, _ in written)  # `f(**options)`: a sketch
        for pname, kind, default in written:
            where = f"{page}: {name}: {pname}"
            if kind == "varkw":  # the options: **kwargs, or the keyword parameters not written
                partial = partial or not any(p.kind is p.VAR_KEYWORD for p in code.values())
                continue
            if pname not in code:
                wrong.append(f"{where}: no such parameter")
                continue
            p = code[pname]
            if starred and (kind == "keyword") != (p.kind is p.KEYWORD_ONLY):
                wrong.append(f"{where}: written {kind}, the code's is {p.kind.name}")
            if default is not None:
                try:
                    value = ast.literal_eval(default)
                except ValueError:
                    continue
                if isinstance(value, list):
                    value = tuple(value)
                if p.default is p.empty or p.default != value:
                    wrong.append(f"{where}: written default {value!r}, the code's {p.default!r}")
        if not partial:
            missing = [k for k, v in code.items() if v.kind not in (v.VAR_KEYWORD, v.VAR_POSITIONAL)
                       and k not in {w[0] for w in written}]
            if missing:
                wrong.append(f"{page}: {name}: the code's {missing} are not written (add them, or '...')")
    assert found >= 10
    assert not wrong, wrong


def test_the_dotted_names_of_the_pages_exist():
    """Every `fsof_torch.a.b` and `fs.a.b` a page names is a module or an attribute the package has,
    and so is every one the library's own docstrings and comments name (`help()` is a page too:
    two of them pointed to ``fsof_torch.io.check_rigid_poses``, which fsof_torch.io does not have)."""
    missing = []
    for page in [*PAGES, *sorted((ROOT / "fsof_torch").rglob("*.py"))]:
        for m in re.finditer(r"(?<![\w./])(?:fsof_torch|fs)((?:\.\w+)+)", page.read_text()):
            parts = ["fsof_torch", *m.group(1).strip(".").split(".")]
            for i in range(len(parts), 0, -1):
                try:
                    obj = importlib.import_module(".".join(parts[:i]))
                    break
                except ImportError:
                    continue
            for part in parts[i:]:
                obj = getattr(obj, part, None)
                if obj is None:
                    missing.append(f"{page.name}: {m.group(0)}")
                    break
    assert not missing, missing


def _written_calls():
    """The other ``name(...)`` spans of the pages (inline code, and Python blocks that are not
    code): a call such as ``ImageGate(require_evidence=False)``, or a signature without a bare
    ``*`` such as ``Camera.padded(left, top, right=0, bottom=0)``."""
    for page in PAGES:
        spans = [code for _, code in _python_blocks(page) if not _runs(code)]
        spans += re.findall(r"`([^`]+)`", _without_fences(page.read_text()))
        for span in spans:
            m = re.fullmatch(r"\s*([A-Za-z_][\w.]*)\((.*)\)\s*", span, re.S)
            if not m or re.search(r"(^|,)\s*\*\*?\w*\s*(,|$)", m.group(2)):
                continue  # not a call, or a signature with a bare * (the test above)
            try:
                call = ast.parse(span.strip().replace("\\|", "|"), mode="eval").body
            except SyntaxError:
                continue  # a sketch: `f(x, y=, ...)`
            if not isinstance(call, ast.Call) or not isinstance(call.func, (ast.Name, ast.Attribute)):
                continue  # `f(a)(b)`: the second call is another callable's
            obj = _resolve(m.group(1))
            if obj is None:
                continue
            try:
                yield page.name, span.strip(), call, inspect.signature(obj).parameters
            except (TypeError, ValueError):
                continue


def test_written_calls_name_the_codes_parameters():
    """Every keyword a page passes exists; where a span reads as the signature (its positional
    arguments bare names, the first one the code's first parameter) the positional names are the
    code's, in order, and a written default is the code's."""
    found, wrong = 0, []
    for page, span, call, code in _written_calls():
        found += 1
        code = {k: v for k, v in code.items() if k != "self"}
        takes_any = any(p.kind is p.VAR_KEYWORD for p in code.values())
        for keyword in call.keywords:
            if keyword.arg is not None and keyword.arg not in code and not takes_any:
                wrong.append(f"{page}: {span}: no parameter {keyword.arg!r}")
        positional = [k for k, v in code.items() if v.kind in (v.POSITIONAL_ONLY, v.POSITIONAL_OR_KEYWORD)]
        names = [a.id for a in call.args if isinstance(a, ast.Name)]
        if not names or len(names) != len(call.args) or names[:1] != positional[:1]:
            continue  # a call with values, or a name of the page's own (`refine_flow(DIS, ...)`)
        if names != positional[:len(names)]:
            wrong.append(f"{page}: {span}: positional {names}, the code's {positional}")
        for keyword in call.keywords:
            if keyword.arg not in code:
                continue
            try:
                value = ast.literal_eval(keyword.value)
            except ValueError:
                continue
            value = tuple(value) if isinstance(value, list) else value
            if value is not Ellipsis and code[keyword.arg].default != value:
                wrong.append(f"{page}: {span}: written default {value!r}, the code's "
                             f"{code[keyword.arg].default!r}")
    assert found >= 30
    assert not wrong, wrong


def test_the_options_table_of_detect_road_is_its_signature():
    """docs/auto-road.md's table: every option of detect_road with its default."""
    from fsof_torch import detect_road

    text = (DOCS / "auto-road.md").read_text()
    table = text[text.index("| option | default | meaning |"):]
    table = table[:table.index("\n\n")]
    rows = {}
    for line in table.splitlines()[2:]:
        names, defaults = (cell.strip() for cell in line.strip("|").split("|")[:2])
        names = re.findall(r"`(\w+)`", names)
        defaults = [d.strip() for d in defaults.split(",")] if len(names) > 1 else [defaults]
        rows.update(zip(names, defaults * len(names) if len(defaults) == 1 else defaults))
    params = {k: v for k, v in inspect.signature(detect_road).parameters.items()
              if v.kind is v.KEYWORD_ONLY}
    assert set(rows) == set(params)
    for name, written in rows.items():
        default = params[name].default
        if written in ("auto", "image estimator"):  # None, (), or what the function picks
            assert default is None or default == (), (name, default)
        else:
            assert ast.literal_eval(written) == default, (name, written, default)


def test_benchmarks_md_lists_every_script():
    text = (DOCS / "benchmarks.md").read_text()
    table = text[text.index("| script | measures | figures |"):]
    listed = set(re.findall(r"^\| `(\w+\.py)`", table[:table.index("\n\n")], re.M))
    assert listed == {p.name for p in (ROOT / "benchmarks").glob("*.py")}


# -- the jobs' options ---------------------------------------------------------------------------

def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings if s.startswith("--") and s != "--help"}


def test_jobs_md_lists_the_refine_jobs_options():
    from refine.options import build_parser

    text = (DOCS / "jobs.md").read_text()
    table = text[text.index("### Options"):text.index("The odometry variants:")]
    written = set(re.findall(r"^\| `(--[\w-]+)|, `(--[\w-]+)", table, re.M))
    written = {a or b for a, b in written}
    assert written == _options(build_parser())


def test_jobs_md_writes_the_refine_options_values_as_the_help_does():
    """The options table writes each option's value as ``--help`` does (``--height M``, ``--out
    DIR``): the help once wrote ``--out OUT``, ``--kitti15 PATH``, ``--scale SCALE`` for the
    table's ``DIR``, ``DIR``, ``PX``. (Options with choices: the table lists them in words.)"""
    from refine.options import build_parser

    text = (DOCS / "jobs.md").read_text()
    table = text[text.index("### Options"):text.index("The odometry variants:")]
    first = [re.split(r"(?<!\\)\|", row)[1] for row in table.splitlines() if row.startswith("| `--")]
    written = {m[0]: m[1] for cell in first for m in re.findall(r"`(--[\w-]+)(?: ([^`]+))?`", cell)}
    parser = build_parser()
    formatter = parser._get_formatter()
    shown = {option: formatter._format_args(action, action.dest.upper()) if action.nargs != 0 else ""
             for action in parser._actions if action.choices is None for option in action.option_strings
             if option in written}
    assert {o: written[o].replace("\\|", "|") for o in shown} == shown


def test_jobs_md_names_what_a_record_holds_about_an_auto_road():
    """docs/jobs.md's record (``pairs/<pair>.json``) names every field ``--road auto`` adds to it
    (the detection's flag, reason, coverage, pixels and step), and the road pixels used."""
    import types

    from fsof_torch import render_pair
    from refine.job import road_mask

    p = render_pair("default", 1, size=(96, 320))
    _, _, info = road_mask({"image1": p["image1"], "image2": p["image2"]}, p["flow"], p["camera"],
                           types.SimpleNamespace(road_auto=True, road_options={}))
    text = (DOCS / "jobs.md").read_text()
    record = text[text.index("**A record**"):text.index("**What the metrics cost.**")]
    assert set(info) >= {"road_flag", "road_reason", "road_coverage", "road_auto_pixels", "road_max_height_m"}
    assert {k for k in [*info, "road_pixels"] if f"`{k}`" not in record} == set()


@pytest.mark.parametrize("name", ["synth", "train", "tables", "noise", "vflow"])
def test_jobs_md_lists_each_eval_subcommands_options(name):
    text = (DOCS / "jobs.md").read_text()
    start = text.index(f"- `{name}`: ", text.index("Options:\n\n- `synth`"))
    item = text[start:text.index("\n- ", start + 1)] if "\n- " in text[start + 1:] else text[start:]
    item = item[:item.index("\n\n")] if "\n\n" in item else item
    parser = argparse.ArgumentParser()
    importlib.import_module(f"eval.{name}").add_arguments(parser)
    assert set(re.findall(r"`(--[\w-]+)", item)) >= _options(parser)
    assert set(re.findall(r"`(--[\w-]+)", item)) <= _options(parser) | {"--kitti15"}


@pytest.mark.parametrize("name", ["tables", "noise", "vflow"])
def test_jobs_md_says_where_an_eval_json_goes_as_the_help_does(name):
    """``--json PATH`` of these subcommands replaces ``DIR/<name>.json`` (their --help says so): the
    option list says so too, not that the JSON is written there as well."""
    text = (DOCS / "jobs.md").read_text()
    start = text.index(f"- `{name}`: ", text.index("Options:\n\n- `synth`"))
    parser = argparse.ArgumentParser()
    importlib.import_module(f"eval.{name}").add_arguments(parser)
    (json_help,) = [a.help for a in parser._actions if "--json" in a.option_strings]
    assert json_help == f"write the JSON here instead of DIR/{name}.json"
    item = text[start:text.index("\n\n", start)]
    assert f"`--json PATH` (the JSON is written there instead of `DIR/{name}.json`)" in item


# -- the commands --------------------------------------------------------------------------------

def _commands():
    """(page, line, words after `python`) of every command the pages give: the lines of bash and
    plain blocks (continuations joined, comments dropped) and inline spans `python ...`."""
    for page in PAGES:
        text = page.read_text()
        for m in FENCE.finditer(text):
            if m.group(2) not in ("bash", ""):
                continue
            start = text[:m.start()].count("\n") + 2
            for k, line in enumerate(m.group(3).replace("\\\n", " ").splitlines()):
                for part in re.split(r"&&|;", line.split("  #")[0]):
                    yield page.name, start + k, part.split()
        plain = _without_fences(text)
        for m in re.finditer(r"`((?:\w+=\S+ )*(?:python|torchrun) [^`]+)`", plain):
            yield page.name, plain[:m.start()].count("\n") + 1, m.group(1).split()


def _script_options(path: Path) -> set[str]:
    """The options a benchmark script's parser adds: the `--` strings of its add_argument calls."""
    tree = ast.parse(path.read_text())
    return {a.value for node in ast.walk(tree) if isinstance(node, ast.Call)
            and getattr(node.func, "attr", None) == "add_argument"
            for a in node.args if isinstance(a, ast.Constant) and str(a.value).startswith("--")} | {"--help"}


def test_the_commands_of_the_docs_name_existing_scripts_and_options():
    """Every `python -m refine`, `python -m eval NAME` and `python benchmarks/x.py` command of the
    pages names a script that exists and only options its parser has."""
    from eval.__main__ import SUBCOMMANDS
    from refine.options import build_parser

    def eval_options(name):
        parser = argparse.ArgumentParser()
        importlib.import_module(SUBCOMMANDS[name][0]).add_arguments(parser)
        return _options(parser) | {"--help"}

    checked, wrong = 0, []
    for page, line, words in _commands():
        launcher = next((i for i, w in enumerate(words) if w in ("python", "torchrun")), None)
        if launcher is None:
            continue
        words = words[launcher + 1:]
        if words[:1] != ["-m"] and words[:1] != [] and not words[0].endswith(".py"):
            words = words[words.index("-m"):] if "-m" in words else []  # torchrun's own options
        if words[:2] == ["-m", "refine"]:
            options = _options(build_parser()) | {"--help"}
        elif words[:2] == ["-m", "eval"] and len(words) > 2 and words[2] in SUBCOMMANDS:
            options = eval_options(words[2])
        elif words[:1] and words[0].endswith(".py"):
            script = ROOT / words[0]
            if not script.is_file():
                wrong.append(f"{page}:{line}: no script {words[0]}")
                continue
            options = _script_options(script)
        else:
            continue  # python -c, -m pytest, -m venv, -m cProfile ..., python -m eval alone
        checked += 1
        used = {re.sub(r"[^\w-].*", "", w.lstrip("[")) for w in words if w.lstrip("[").startswith("--")}
        if used - options:
            wrong.append(f"{page}:{line}: {' '.join(words[:2])}: no option {sorted(used - options)}")
    assert checked >= 100
    assert not wrong, wrong
