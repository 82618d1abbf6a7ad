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
    listed = re.findall(r"``(\w+)``", doc.partition("The flat module paths of earlier versions stay:")[2])
    assert {"fit", "flow_model", "camera", "metrics"} <= set(listed)
    for name in listed:
        module = importlib.import_module(f"fsof_torch.{name}")
        assert sys.modules[f"fsof_torch.{name}"] is module and getattr(fsof_torch, name) is module, name
    for sub in re.findall(r"``(\w+)``", doc.split("Subpackages:")[1].split(".")[0]):
        assert importlib.import_module(f"fsof_torch.{sub}") is getattr(fsof_torch, sub), sub
