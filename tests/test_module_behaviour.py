"""The library's modules and stateful objects as training and deployment code uses them: copied,
pickled, in DataLoader workers, saved and loaded, cast, wrapped in DistributedDataParallel and
called from several threads at once (docs/refinement.md, "In training and deployment code")."""

from __future__ import annotations

import copy
import pickle
import warnings
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

import fsof_torch as fs
from fsof_torch.refinement.gate import ImageGate


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pairs():
    return [fs.render_pair("default", k, size=(96, 320)) for k in (1, 5)]


def _inputs(pair, seed):
    gt = pair["flow"][None]
    pred = gt + seed * torch.randn(gt.shape, generator=torch.Generator().manual_seed(seed))
    return pred, pair["road"][None], pair["camera"], pair["odometry"], (pair["image1"][None], pair["image2"][None])


def _equal(a, b):
    """Refiner outputs (tensors, containers, cameras, fits) equal bit for bit."""
    if isinstance(a, torch.Tensor):
        return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.nan_to_num(), b.nan_to_num())
    if isinstance(a, fs.Camera):
        return all(_equal(getattr(a, k), getattr(b, k)) for k in ("K", "height", "roll", "pitch"))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b if isinstance(a, (str, int, float, bool, type(None))) else True


# -- repr -----------------------------------------------------------------------------------------

def test_refiner_repr_shows_the_options_that_are_not_the_defaults():
    assert repr(fs.FreespaceRefiner()) == "FreespaceRefiner(mode='replace', estimator=None, gate='auto')"
    assert repr(fs.FreespaceRefiner(mode="confidence", fit="flow")) == (
        "FreespaceRefiner(mode='confidence', scale=2.0, fit='flow', gate='auto')")
    text = repr(fs.FreespaceRefiner(min_pixels=10, warn=False, flow_keys="flow_up", fit="flow", fit_pitch=True,
                                    fit_options={"max_iter": 5}))
    assert text == ("FreespaceRefiner(mode='replace', fit='flow', gate='auto', min_pixels=10, flow_keys=('flow_up',), "
                    "warn=False, fit_pitch=True, fit_options={'max_iter': 5})")


def test_component_reprs_show_their_options():
    """The estimators' and the gate's reprs left their further options out: a refiner with
    ImageMotionEstimator(fine_points=20000) or ImageGate(z=3.0) printed as the default one."""
    assert repr(fs.FlowMotionEstimator(model="plane", max_iter=5)) == (
        "FlowMotionEstimator(model='plane', fixed=('roll', 'pitch'), max_iter=5)")
    assert repr(fs.ImageMotionEstimator(fine_points=20000, smooth_sigma=1.0, odometry_sigma={"z_d": 0.1})) == (
        "ImageMotionEstimator(model='plane', flow_start=True, odometry_sigma={'z_d': 0.1}, fine_points=20000, "
        "smooth_sigma=1.0)")
    assert repr(ImageGate(z=3.0, contrast=5.0)) == ("ImageGate(grid=(8, 16), objects=True, points=6000, margin=0.0, "
                                                   "occlusion=0.35, require_evidence=True, z=3.0, contrast=5.0)")
    assert repr(ImageGate()) == ("ImageGate(grid=(8, 16), objects=True, points=6000, margin=0.0, occlusion=0.35, "
                                 "require_evidence=True)")
    text = repr(fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(fine_points=20000)))
    assert text == ("FreespaceRefiner(mode='replace', estimator=ImageMotionEstimator(model='plane', flow_start=True, "
                    "fine_points=20000), gate='auto')")


def test_wrapper_repr_shows_its_own_options():
    net = fs.TinyRAFT(seed=0, iters=1)
    first = repr(fs.FreespaceRefined(net)).splitlines()[:2]
    assert first == ["FreespaceRefined(", "  road=None, pad=None, image_range=(0.0, 255.0)"]
    text = repr(fs.FreespaceRefined(net, road="auto", road_options={"z": 3.0}, pad=fs.InputPadder(8),
                                    image_range=(-1, 1)))
    assert text.splitlines()[1] == ("  road='auto', road_options={'z': 3.0}, pad=InputPadder(8, mode='sintel', "
                                    "pad_mode='replicate'), image_range=(-1.0, 1.0)")


# -- copies, pickles, DataLoader workers ------------------------------------------------------------

def _refiners():
    return {
        "images": (fs.FreespaceRefiner(), lambda r, i: r(i[0], i[1], i[2], images=i[4])),
        "odometry": (fs.FreespaceRefiner(mode="confidence"), lambda r, i: r(i[0], i[1], i[2], i[3], images=i[4])),
        "flow": (fs.FreespaceRefiner(estimator=fs.FlowMotionEstimator(model="plane"), gate=ImageGate(grid=(4, 8))),
                 lambda r, i: r(i[0], i[1], i[2], images=i[4])),
        "auto": (fs.FreespaceRefiner(), lambda r, i: r(i[0], "auto", i[2], images=i[4])),
    }


def test_copies_and_pickles_refine_as_the_original(pairs):
    inputs = _inputs(pairs[0], 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (refiner, call) in _refiners().items():
            want = call(refiner, inputs)
            assert bool(want.refined.all()), name
            for copied in (copy.deepcopy(refiner), pickle.loads(pickle.dumps(refiner, protocol=5))):
                assert _equal(call(copied, inputs), want), name


def test_wrapper_and_losses_pickled_give_the_same_outputs(pairs):
    image1, image2 = (torch.stack([p[k] for p in pairs]) for k in ("image1", "image2"))
    batch = fs.datasets.collate([dict(p) for p in pairs])
    model = fs.FreespaceRefined(fs.TinyRAFT(seed=0, iters=2))
    loss = fs.CompositeLoss({"u": (1.0, fs.UnsupervisedFlowLoss()), "f": (0.1, fs.FreespaceFlowLoss()),
                             "fit": (0.1, fs.FreespaceFlowLoss(odometry="fit"))})
    with torch.no_grad():
        want = model(image1, image2, camera=batch["camera"], mask=batch["road"])
        total = loss(want, batch)[0]
        for copied in (copy.deepcopy(model), pickle.loads(pickle.dumps(model, protocol=5))):
            assert _equal(copied(image1, image2, camera=batch["camera"], mask=batch["road"]), want)
        assert torch.equal(pickle.loads(pickle.dumps(loss))(want, batch)[0], total)


class _RefiningCollate:
    """``collate`` and the refiner with the images, in a DataLoader worker."""

    def __init__(self, refiner):
        self.refiner = refiner

    def __call__(self, items):
        batch = fs.datasets.collate(items)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = self.refiner(batch["flow"] + 1.0, batch["road"], batch["camera"],
                               images=(batch["image1"], batch["image2"]))
        return out.flow, out.refined


def test_a_dataset_and_the_refiner_in_dataloader_workers():
    from torch.utils.data import DataLoader

    dataset = fs.datasets.SceneDataset("default", 4, size=(64, 224))
    collate = _RefiningCollate(fs.FreespaceRefiner())
    want = [collate([dataset[i], dataset[i + 1]]) for i in (0, 2)]
    got = list(DataLoader(dataset, batch_size=2, num_workers=2, collate_fn=collate))
    assert _equal(got, want) and all(bool(refined.all()) for _, refined in got)


# -- state, saving, casts ---------------------------------------------------------------------------

def test_state_dicts(pairs, tmp_path):
    image1, image2 = pairs[0]["image1"][None], pairs[0]["image2"][None]
    road, camera = pairs[0]["road"][None], pairs[0]["camera"]
    a, b = (fs.FreespaceRefined(fs.TinyRAFT(seed=s, iters=2)) for s in (0, 1))
    assert all(k.startswith("net.") for k in a.state_dict()) and list(a.state_dict()) == list(b.state_dict())
    torch.save(a.state_dict(), tmp_path / "model.pt")
    assert str(b.load_state_dict(torch.load(tmp_path / "model.pt"))) == "<All keys matched successfully>"
    with torch.no_grad():
        assert _equal(a(image1, image2, camera=camera, mask=road), b(image1, image2, camera=camera, mask=road))
    for module in (fs.FreespaceRefiner(), fs.UnsupervisedFlowLoss(), fs.FreespaceFlowLoss(),
                   fs.CompositeLoss({"f": (1.0, fs.FreespaceFlowLoss())})):
        assert module.state_dict() == {} and list(module.buffers()) == []   # (options, no tensors)
    # a whole module, a camera (a batch of collate's) are pickles: refused by torch.load's default
    torch.save(camera, tmp_path / "camera.pt")
    with pytest.raises(pickle.UnpicklingError):
        torch.load(tmp_path / "camera.pt")
    with torch.serialization.safe_globals([fs.Camera]):
        assert _equal(torch.load(tmp_path / "camera.pt"), camera)


def test_casts_of_the_wrapper(pairs):
    image1, image2 = pairs[0]["image1"][None], pairs[0]["image2"][None]
    road, camera, odometry = pairs[0]["road"][None], pairs[0]["camera"], pairs[0]["odometry"]
    with torch.no_grad():
        _, want = fs.FreespaceRefined(fs.TinyRAFT(seed=0, iters=2))(image1, image2, camera=camera, mask=road,
                                                                   odometry=odometry, return_info=True)
        for cast, dtype in (("double", torch.float64), ("half", torch.float32), ("bfloat16", torch.float32)):
            model = getattr(fs.FreespaceRefined(fs.TinyRAFT(seed=0, iters=2)), cast)()
            flows, info = model(image1, image2, camera=camera, mask=road, odometry=odometry, return_info=True)
            assert flows[-1].dtype == next(model.parameters()).dtype and bool(info.refined.all()), cast
            assert info.flow_model.dtype == dtype, cast   # (geometry at float32 at least)
            torch.testing.assert_close(info.flow_model.to(torch.float64), want.flow_model.to(torch.float64),
                                       rtol=0, atol=1e-3)


def test_training_after_a_call_under_inference_mode(pairs):
    """A validation loop's call under torch.inference_mode, then a training step with gradients
    (in a fresh process the library's cached constants are made in the first call)."""
    import subprocess
    import sys

    code = """if True:
        import warnings, torch, fsof_torch as fs
        torch.set_num_threads(1)
        warnings.simplefilter("ignore")
        batch = fs.datasets.collate([fs.render_pair("default", 1, size=(96, 320))])
        loss = fs.CompositeLoss({"u": (1.0, fs.UnsupervisedFlowLoss()), "f": (0.1, fs.FreespaceFlowLoss())})
        for refiner, kw in ((fs.FreespaceRefiner(), {"odometry": batch["odometry"]}),
                            (fs.FreespaceRefiner(mode="confidence"), {})):
            model = fs.FreespaceRefined(fs.TinyRAFT(seed=0, iters=1), refiner)
            with torch.inference_mode():
                model.eval()(batch["image1"], batch["image2"], camera=batch["camera"], mask=batch["road"], **kw)
            height = batch["camera"].height.clone().requires_grad_()   # (a gradient to the camera too)
            camera = batch["camera"].replace(height=height)
            flows = model.train()(batch["image1"], batch["image2"], camera=camera, mask=batch["road"], **kw)
            loss(flows, {**batch, "camera": camera})[0].backward()
            assert all(p.grad is not None for p in model.parameters()) and bool(height.grad.abs().sum() > 0)
        print("trained")
    """
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == "trained", done.stderr[-2000:]


# -- DistributedDataParallel, threads ---------------------------------------------------------------

def test_distributed_data_parallel_of_the_wrapper(tmp_path):
    """The wrapper under DistributedDataParallel (gloo, one process) gives the gradients it gives
    alone. Run in a process of its own that ends with ``os._exit`` once it has printed its
    verdict, without tearing gloo down: torch 2.13 can deadlock there (the process group's
    destructor, holding the GIL, joins a gloo worker that waits for the GIL to release its last
    work's thread-local state; seen under load, the suite then hung), which is torch's, not the
    wrapper's."""
    import subprocess
    import sys

    code = f"""if True:
        import os, warnings, torch, torch.distributed as dist, fsof_torch as fs
        from torch.nn.parallel import DistributedDataParallel
        torch.set_num_threads(1)
        warnings.filterwarnings("ignore", "Grad strides do not match")  # (torch's, on a 1x1 convolution)
        batch = fs.datasets.collate([fs.render_pair("default", k, size=(96, 320)) for k in (1, 5)])
        loss = fs.CompositeLoss({{"u": (1.0, fs.UnsupervisedFlowLoss()), "f": (0.1, fs.FreespaceFlowLoss())}})
        dist.init_process_group("gloo", init_method={f"file://{tmp_path / 'store'}"!r}, rank=0, world_size=1)
        grads = []
        for wrap in (False, True):
            model = fs.FreespaceRefined(fs.TinyRAFT(seed=0, iters=1), fs.FreespaceRefiner(mode="confidence"))
            run = DistributedDataParallel(model) if wrap else model
            flows, _ = run(batch["image1"], batch["image2"], camera=batch["camera"], mask=batch["road"],
                           odometry=batch["odometry"], return_info=True)
            loss(flows, batch)[0].backward()
            grads.append(torch.cat([p.grad.flatten() for p in model.parameters()]))
        print("equal" if torch.equal(grads[0], grads[1]) and bool(grads[0].abs().sum() > 0) else "differ", flush=True)
        os._exit(0)
    """
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip() == "equal", done.stderr[-2000:]


def test_one_refiner_called_from_several_threads(pairs):
    inputs = [_inputs(p, s) for p, s in zip(pairs, (1, 2))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (refiner, call) in list(_refiners().items())[::3]:   # (images; auto)
            want = [call(refiner, i) for i in inputs]
            with ThreadPoolExecutor(4) as pool:
                got = list(pool.map(lambda i: call(refiner, i), inputs * 2))
            assert all(_equal(g, want[k % 2]) for k, g in enumerate(got)), name
