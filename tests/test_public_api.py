"""The public contract (DESIGN.md §9): names other code relies on must not disappear."""

import importlib

import pytest

import fsof_torch

CONTRACT = [
    "Camera", "displacement_flow", "velocity_flow", "DisplacementFlow", "VelocityFlow",
    "fit_displacement", "fit_velocity", "fit_photometric", "warp_backward", "photometric_error",
    "FreespaceRefiner", "FreespaceRefined", "FreespaceFlowLoss", "UnsupervisedFlowLoss", "TinyRAFT",
    "detect_freespace", "detect_road", "vflow_map", "render_pair", "ego_motion_from_pose",
    "ego_motion_from_ackermann", "read_kitti_flow", "write_kitti_flow", "read_flo", "write_flo",
    # the road-motion models and their fit (DESIGN.md §9, §10)
    "fit_road", "road_flow", "road_homography", "RoadFit", "ROAD_MODELS", "decompose_homography",
    "plane_from_pose", "road_motion",
]
METRICS = ["angular_error", "endpoint_error", "u_error", "v_error", "outlier_rate", "flow_metrics"]


@pytest.mark.parametrize("name", CONTRACT)
def test_contract_name_exported(name):
    assert name in fsof_torch.__all__
    assert getattr(fsof_torch, name) is not None


@pytest.mark.parametrize("name", METRICS)
def test_metrics_names(name):
    assert callable(getattr(fsof_torch.evaluation.metrics, name))


def test_all_names_resolve():
    missing = [n for n in fsof_torch.__all__ if not hasattr(fsof_torch, n)]
    assert missing == []


@pytest.mark.parametrize("job", ["refine", "eval"])
def test_jobs_have_main_and_help(job, capsys):
    module = importlib.import_module(f"{job}.__main__")
    try:
        code = module.main(["--help"])
    except SystemExit as exc:  # argparse exits after printing help
        code = exc.code
    assert code in (0, None)
    assert "usage" in capsys.readouterr().out.lower()


def test_the_flat_module_paths_are_modules_as_the_docstring_lists():
    """Every flat module path the package docstring lists imports as the module that now holds it,
    and is that module as an attribute too (``import fsof_torch.fit; fsof_torch.fit.fit_road`` was
    an AttributeError); ``pose``, listed, was none. ``fsof_torch.fit_photometric`` is the function;
    its module path serves ``from``-imports."""
    import re
    import sys

    import fsof_torch.fit
    import fsof_torch.flow_model

    assert fsof_torch.fit.fit_road is fsof_torch.fit_road
    assert fsof_torch.flow_model.road_flow is fsof_torch.road_flow
    assert callable(fsof_torch.fit_photometric)
    from fsof_torch.fit_photometric import fit_image

    assert fit_image is fsof_torch.fit_image
    doc = " ".join(fsof_torch.__doc__.split())
    assert "``pose``" not in doc
    listed = re.findall(r"``(\w+)``", doc.partition("Short module paths are aliases of their modules:")[2])
    assert {"fit", "flow_model", "camera", "metrics"} <= set(listed)
    for name in listed:
        module = importlib.import_module(f"fsof_torch.{name}")
        assert sys.modules[f"fsof_torch.{name}"] is module and getattr(fsof_torch, name) is module, name
    for sub in re.findall(r"``(\w+)``", doc.split("Subpackages:")[1].split(".")[0]):
        assert importlib.import_module(f"fsof_torch.{sub}") is getattr(fsof_torch, sub), sub


# -- result objects: repr, equality ----------------------------------------------------------------

@pytest.fixture(scope="module")
def results():
    """One of each result object, from a batch of 2 rendered pairs at KITTI's width."""
    import warnings

    import torch

    torch.set_num_threads(1)
    batch = fsof_torch.collate([fsof_torch.render_pair("default", k, size=(128, 1242)) for k in (1, 2)])
    flow, road, camera = batch["flow"], batch["road"], batch["camera"]
    images = (batch["image1"], batch["image2"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fsof_torch.refine_flow(flow + 0.5, road, camera, images=images)
        auto = fsof_torch.refine_flow(flow, "auto", camera, images=images)
        return {
            "Camera": camera,
            "RoadFit": fsof_torch.fit_road(flow, road, camera, model="plane"),
            "RefineOutput": out,
            "GateResult": out.gate,
            "RoadDetection": auto.road,
            "FreespaceDetection": fsof_torch.detect_freespace(flow, camera, mask=road, return_details=True),
            "VFlowCurve": fsof_torch.fit_vflow_curve(flow, road),
        }


RESULTS = ["Camera", "RoadFit", "RefineOutput", "GateResult", "RoadDetection", "FreespaceDetection", "VFlowCurve"]


@pytest.mark.parametrize("name", RESULTS)
def test_result_reprs_are_short_and_name_their_fields(results, name):
    """A result's repr lists its fields with the tensors of more than a few values as their shape
    and dtype (torch's repr of the flows and masks ran to 100-230 lines, 5-15 kB)."""
    import dataclasses

    obj = results[name]
    assert type(obj).__name__ == name
    text = repr(obj)
    fields = obj._fields if isinstance(obj, tuple) else [f.name for f in dataclasses.fields(obj) if f.repr]
    assert text.startswith(f"{name}(") and all(f"{k}=" in text for k in fields), text
    assert len(text) < 2500 and text.count("\n") == 0, text
    if name == "RoadFit":
        assert "flow=tensor(shape=(2, 2, 128, 1242), dtype=torch.float32)" in text
        assert "model='plane'" in text and "success=tensor([True, True])" in text


@pytest.mark.parametrize("name", ["RoadFit", "RoadDetection", "FreespaceDetection", "VFlowCurve"])
def test_result_dataclasses_compare_by_identity_as_cameras_do(results, name):
    """``==`` on a result holding tensors raised torch's 'Boolean value of Tensor with more than one
    value is ambiguous', and the results were unhashable; like a Camera they compare by identity."""
    import copy

    obj = results[name]
    assert obj == obj and obj != copy.copy(obj) and {obj: 1}[obj] == 1


def test_a_sequence_fit_compares_by_identity_and_prints_short(results):
    import copy

    import torch

    from fsof_torch.estimation.sequence import SequenceFit

    fit = SequenceFit(fits=[results["RoadFit"]] * 6, params={"z_d": torch.ones(6)}, mounting={"roll": 0.0},
                      camera=results["Camera"], first_pass={}, success=torch.ones(6, dtype=torch.bool),
                      calibrated_from=6)
    assert fit == fit and fit != copy.copy(fit) and {fit: 1}[fit] == 1
    text = repr(fit)
    assert text.count("RoadFit(") == 4 and "... (6 items)" in text and len(text) < 6000, text


def test_the_named_tuple_results_of_many_frames_print_on_one_line():
    """docs/conventions.md: an ``EgoMotion`` and a ``VFlowMap`` print on one line like the other
    results; torch's repr of 20 frames' motion or of a V-flow histogram ran to 20-40 lines."""
    import torch

    motion = fsof_torch.ego_motion_from_ackermann(torch.linspace(5.0, 15.0, 20), torch.zeros(20), 2.7, 0.1)
    text = repr(motion)
    assert text.count("\n") == 0 and text.startswith("EgoMotion(x_d=tensor(shape=(20,), dtype=torch.float32)"), text
    assert "rotation_residual=tensor(shape=(20, 3), dtype=torch.float32)" in text
    assert repr(motion._replace(x_d=torch.tensor([0.5]))).count("tensor([0.5000])") == 1  # few values: as torch prints them
    flow = torch.zeros(1, 2, 48, 160)
    hist = fsof_torch.vflow_map(flow, bins=16)
    assert repr(hist) == ("VFlowMap(histogram=tensor(shape=(1, 48, 16), dtype=torch.float32), "
                          "edges=tensor(shape=(17,), dtype=torch.float32))")
    histogram, edges = hist  # still a tuple
    assert histogram.shape == (1, 48, 16) and edges.shape == (17,)


def test_road_model_repr_leaves_out_its_private_map():
    assert repr(fsof_torch.ROAD_MODELS["paper"]) == (
        "RoadModel(name='paper', params=('x_d', 'z_d', 'yaw', 'roll', 'pitch'), units=('m', 'm', 'rad', 'rad', 'rad'), "
        "mounting=('roll', 'pitch'), velocity=False)")


def test_public_classes_document_their_methods_and_properties():
    """``help(fs.Camera.fx)``, ``help(fs.FreespaceRefiner.forward)`` and the like rendered no
    text: the properties of Camera, the modules' ``forward`` and the accumulator's counters had none."""
    import inspect
    import pydoc

    missing = []
    for name in fsof_torch.__all__:
        obj = getattr(fsof_torch, name)
        if not inspect.isclass(obj):
            continue
        for attr, value in vars(obj).items():
            if attr.startswith("_") or attr == "extra_repr" or not (callable(value) or isinstance(value, property)):
                continue
            if not (getattr(value, "__doc__", None) or "").strip():
                missing.append(f"{name}.{attr}")
        assert obj.__name__ in pydoc.render_doc(obj, renderer=pydoc.plaintext), name
    assert missing == []


def test_module_reprs_show_their_options():
    """CompositeLoss showed no weights (nor its function terms), TinyRAFT not its iterations."""
    loss = fsof_torch.CompositeLoss({"u": (1.0, fsof_torch.UnsupervisedFlowLoss()), "x": (0.5, len),
                                     "f": (0.1, fsof_torch.FreespaceFlowLoss())})
    assert repr(loss).splitlines()[1] == "  weights={'u': 1.0, 'x': 0.5, 'f': 0.1}, functions={'x': len}"
    assert repr(fsof_torch.TinyRAFT(iters=2, corr_radius=2)).splitlines()[1] == "  iters=2, corr_levels=3, corr_radius=2"


def test_the_refiner_module_takes_every_option_of_refine_flow_but_road_options():
    """docs/refinement.md: ``FreespaceRefiner(**options)`` is ``refine_flow``'s twin, with all its
    options but ``road_options`` (which the page said nothing of: ``FreespaceRefiner(road_options=...)``
    is a TypeError; ``refine_flow`` and ``FreespaceRefined`` take them)."""
    import inspect
    import re
    from pathlib import Path

    calls = {"flow", "mask", "camera", "odometry", "images", "starts"}
    function = set(inspect.signature(fsof_torch.refine_flow).parameters) - calls
    module = set(inspect.signature(fsof_torch.FreespaceRefiner).parameters)
    assert function - module == {"road_options"} and module - function == set()
    assert set(fsof_torch.FreespaceRefiner().refine_options()) == module
    assert "road_options" in inspect.signature(fsof_torch.FreespaceRefined).parameters
    page = " ".join((Path(__file__).parents[1] / "docs" / "refinement.md").read_text().split())
    assert re.search(r"Its options are all of `refine_flow`'s but `road_options`", page)
