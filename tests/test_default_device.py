"""The library under a default device that is not its inputs' (``torch.set_default_device("cuda")``
or ``with torch.device("cuda"):`` and tensors read from files on the CPU): what it creates goes to
its inputs' device, or to the CPU where it reads a file or takes numbers, never to the default
device; and a default dtype of float64 leaves float32 results float32.

No GPU is needed: the meta device stands in for the default device. A tensor created there has no
values, so a creation that follows the default device fails or returns meta tensors; the results
here must be the CPU tensors of the same call without it, bit for bit.
"""

import dataclasses
import subprocess
import sys

import pytest
import torch

import fsof_torch as fs
from fsof_torch.estimation import flow_fit

SIZE = (64, 192)  # (pair 0 at this size: the road found by detect_road, flag 'ok')


def _default_device() -> torch.device:
    return torch.empty(0).device


def on_meta(fn, *, context: bool = False):
    """``fn()`` with meta as the default device (set, or a ``with torch.device`` block), restored after."""
    if context:
        with torch.device("meta"):
            return fn()
    before = _default_device()
    torch.set_default_device("meta")
    try:
        return fn()
    finally:
        # (None, not "cpu", where none was set: set to the CPU, torch keeps a device mode that sees
        # every later call of the process)
        torch.set_default_device(None if before.type == "cpu" else before)


def tensors(x, name: str = "out") -> dict:
    """Every tensor and number in a result (dicts, sequences, named tuples, dataclasses, cameras)."""
    if isinstance(x, torch.Tensor):
        return {name: x}
    if isinstance(x, (bool, int, float, str)):
        return {name: x}
    if isinstance(x, fs.Camera):
        return {f"{name}.{k}": getattr(x, k) for k in ("K", "height", "roll", "pitch")}
    if isinstance(x, dict):
        items = x.items()
    elif isinstance(x, tuple) and hasattr(x, "_fields"):
        items = ((k, getattr(x, k)) for k in x._fields)
    elif isinstance(x, (list, tuple)):
        items = enumerate(x)
    elif dataclasses.is_dataclass(x):
        items = ((f.name, getattr(x, f.name)) for f in dataclasses.fields(x))
    else:
        return {}
    out = {}
    for k, v in items:
        out.update(tensors(v, f"{name}.{k}"))
    return out


def assert_same(got, expected) -> None:
    got, expected = tensors(got), tensors(expected)
    assert got.keys() == expected.keys()
    assert expected, "the call returned no tensors"
    for k, e in expected.items():
        g = got[k]
        if isinstance(e, torch.Tensor):
            assert g.device == e.device and g.dtype == e.dtype, (k, g.device, g.dtype, e.device, e.dtype)
            torch.testing.assert_close(g, e, rtol=0, atol=0, equal_nan=True, msg=k)
        else:
            assert g == e or (g != g and e != e), (k, g, e)


@pytest.fixture(scope="module")
def pair():
    p = fs.render_pair("default", 0, size=SIZE)
    noise = torch.randn(p["flow"].shape, generator=torch.Generator().manual_seed(0))
    return {"image1": p["image1"][None], "image2": p["image2"][None], "flow": p["flow"][None],
            "valid": p["valid"][None], "road": p["road"][None], "camera": p["camera"], "odometry": p["odometry"],
            "prediction": p["flow"][None] + 0.5 * noise, "frames": [p["image1"], p["image2"], p["image2"]],
            "poses": torch.stack([p["pose1"], p["pose2"], p["pose2"]]), "rendered": p}


CALLS = {
    "render_pair": lambda p: fs.render_pair("default", 1, size=SIZE),
    "SceneDataset": lambda p: fs.datasets.SceneDataset("default", 2, size=SIZE)[1],
    "refiner_odometry": lambda p: fs.FreespaceRefiner()(p["prediction"], p["road"], p["camera"], p["odometry"]),
    "refiner_flow": lambda p: fs.FreespaceRefiner()(p["prediction"], p["road"], p["camera"]),
    "refiner_images": lambda p: fs.FreespaceRefiner()(p["prediction"], p["road"], p["camera"],
                                                      images=(p["image1"], p["image2"])),
    "refiner_auto": lambda p: fs.FreespaceRefiner()(p["prediction"], "auto", p["camera"],
                                                    images=(p["image1"], p["image2"])),
    "detect_road": lambda p: fs.detect_road(p["image1"], p["image2"], p["camera"]),
    "ImageGate": lambda p: fs.ImageGate()(p["image1"], p["image2"], p["prediction"], p["flow"], p["road"]),
    "fit_image": lambda p: fs.fit_image(p["image1"], p["image2"], p["road"], p["camera"]),
    "fit_velocity": lambda p: fs.fit_velocity(10 * p["flow"], p["road"], p["camera"], 2.7, valid=p["valid"]),
    "fit_velocity_steering": lambda p: fs.fit_velocity(10 * p["flow"], p["road"], p["camera"], 2.7, valid=p["valid"],
                                                       init={"steering": 0.01, "speed": 5.0}),
    "fit_sequence_poses": lambda p: fs.fit_sequence(p["frames"], p["road"][0], p["camera"], poses=p["poses"].tolist()),
    "FreespaceFlowLoss": lambda p: fs.FreespaceFlowLoss()([p["prediction"]], p["road"], p["camera"], p["odometry"]),
    "UnsupervisedFlowLoss_census": lambda p: fs.UnsupervisedFlowLoss(census_weight=1.0)(
        [p["prediction"]], p["image1"], p["image2"], [-p["prediction"]]),
    "CompositeLoss": lambda p: fs.CompositeLoss({"constant": (1.0, lambda flows, image1: 2.5)})(
        [p["prediction"]], {"image1": p["image1"]}),
    "photometric_census": lambda p: fs.photometric_errors(p["image1"], p["image2"], p["prediction"], p["road"],
                                                          kinds=("l1", "census", "ssim")),
    "flow_to_color": lambda p: fs.flow_to_color(p["prediction"]),
    "vflow_curve_numbers": lambda p: fs.vflow_curve(30.0, 1.0, 1.65, 100.0, 20.0),
    "collate": lambda p: fs.collate([p["rendered"], p["rendered"]]),
}


@pytest.mark.parametrize("name", list(CALLS))
def test_default_device_not_used(pair, name):
    call = CALLS[name]
    expected = call(pair)
    if name == "detect_road":  # (the whole detection ran)
        assert expected.flag == ["ok"]
    assert_same(on_meta(lambda: call(pair)), expected)


@pytest.mark.parametrize("name", ["refiner_images", "fit_velocity", "render_pair"])
def test_device_context_not_used(pair, name):
    call = CALLS[name]
    expected = call(pair)
    assert_same(on_meta(lambda: call(pair), context=True), expected)


def test_flow_fit_constant_built_on_the_host(pair, monkeypatch):
    # the fit's constant, cached per dtype and device, first built while the default device is another one
    monkeypatch.setattr(flow_fit, "_BASIS", {})
    got = on_meta(lambda: fs.fit_displacement(pair["flow"], pair["road"], pair["camera"], valid=pair["valid"]))
    assert_same(got, fs.fit_displacement(pair["flow"], pair["road"], pair["camera"], valid=pair["valid"]))


def test_readers_return_cpu_tensors(pair, tmp_path):
    K = torch.tensor([[700.0, 0.0, 60.0], [0.0, 700.0, 20.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    calib = fs.io.kitti.write_kitti_calibration(tmp_path / "calib.txt", K)
    poses_file = fs.write_kitti_poses(tmp_path / "poses.txt", pair["poses"][:2])
    fs.io.layout.write_synthetic_sequence(tmp_path / "clip", [pair["rendered"]])
    read = {"calibration": lambda: fs.read_kitti_calibration(calib, 2),
            "camera": lambda: fs.Camera.from_kitti(calib, height=1.65),
            "poses": lambda: fs.read_kitti_poses(poses_file),
            "carla_camera": lambda: fs.io.carla.carla_camera((60, 80)),
            "synthetic_item": lambda: fs.datasets.SyntheticFlowDataset(tmp_path / "clip")[0]}
    for name, fn in read.items():
        assert_same(on_meta(fn), fn())


def test_import_under_another_default_device():
    # the constants computed at import
    code = "import torch; torch.set_default_device('meta'); import fsof_torch; print('imported')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "imported" in out.stdout, out.stderr[-2000:]


def test_gate_evidence_keeps_the_images_dtype(pair):
    expected = fs.ImageGate()(pair["image1"], pair["image2"], pair["prediction"], pair["flow"], pair["road"])
    torch.set_default_dtype(torch.float64)
    try:
        got = fs.ImageGate()(pair["image1"], pair["image2"], pair["prediction"], pair["flow"], pair["road"])
    finally:
        torch.set_default_dtype(torch.float32)
    assert expected.evidence.dtype == torch.float32
    assert_same(got, expected)


def test_pair_figure_draws_under_another_default_device(pair, tmp_path):
    # the refine job's figure of a pair (its images, flows and errors on the CPU)
    import matplotlib.pyplot as plt

    from fsof_torch.evaluation import figures

    error = (pair["prediction"] - pair["flow"])[0].norm(dim=0, keepdim=True)
    valid = pair["valid"][0]

    def draw():
        fig = figures.pair_figure(flows={"truth": pair["flow"][0], "prediction": pair["prediction"][0]},
                                  errors={"prediction": (error, valid)}, road=pair["road"][0], max_flow=5.0,
                                  error_vmax=2.0, error_label="EPE (px)", title="pair",
                                  images=(pair["image1"][0], pair["image2"][0]), valid=valid)
        try:
            return [im.get_array().copy() for ax in fig.axes for im in ax.get_images()]
        finally:
            plt.close(fig)

    expected = draw()
    got = on_meta(draw)
    assert len(got) == len(expected) > 0
    for g, e in zip(got, expected):
        assert (g == e).all()
    assert (on_meta(lambda: figures.colour_wheel(5.0, 21)) == figures.colour_wheel(5.0, 21)).all()
