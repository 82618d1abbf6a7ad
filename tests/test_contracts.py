"""fsof_torch.refinement.contracts and the drop-in wrapper with the stand-ins of ptlflow's RAFT
and torchvision's RAFT: shapes, colour order, padding, and refinement on the padded grid."""

from __future__ import annotations

from collections import OrderedDict
from typing import NamedTuple

import numpy as np
import pytest
import re
import warnings

import torch
import torch.nn.functional as F

from fsof_torch import Camera, FreespaceRefined, FreespaceRefiner, displacement_flow, refine_flow
from fsof_torch.refinement.contracts import (
    DEFAULT_FLOW_KEYS,
    InputPadder,
    Padding,
    collect_flows,
    finest_flow,
    images_from_ptlflow,
    map_flows,
    ptlflow_inputs,
)
from fsof_torch.training.standins import PtlflowRAFTStandIn, TorchvisionRAFTStandIn

SIZE = (53, 94)  # neither side divisible by 8: padding (left, right, top, bottom) = (1, 1, 1, 2)


@pytest.fixture(scope="module")
def scene():
    """One rendered pair at SIZE: images, road mask, camera (float32) and exact odometry."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=SIZE)
    odo = {k: float(p["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
    return {"image1": p["image1"][None], "image2": p["image2"][None], "road": p["road"][None],
            "camera": p["camera"].to(torch.float32), "odometry": odo}


def _assert_refined(out: torch.Tensor, raw: torch.Tensor, expected: torch.Tensor, mask: torch.Tensor):
    """Outside ``mask`` ``out`` is ``raw`` bit for bit; inside it is ``expected`` to 1e-4 px."""
    m = mask.expand_as(out)
    assert torch.equal(out[~m], raw[~m])
    assert bool(m.any())
    torch.testing.assert_close(out[m], expected[m], atol=1e-4, rtol=0)


# -- structures ----------------------------------------------------------------------------------

class Pair(NamedTuple):
    low: torch.Tensor
    up: torch.Tensor


class TestStructures:
    def test_collect_names_and_order(self):
        a, b = torch.zeros(1, 2, 4, 6), torch.ones(1, 3, 2, 8, 12)
        out = {"flows": b, "occs": torch.zeros(1, 1, 1, 8, 12), "flow_small": a}
        names = [n for n, _ in collect_flows(out)]
        assert names == ["flow['flows']", "flow['flow_small']"]
        name, finest = finest_flow(collect_flows(out))
        assert name == "flow['flows']" and torch.equal(finest, b[:, -1])

    def test_finest_flow_prefers_a_final_flow_to_a_warm_start_of_its_size(self):
        a, b, c = torch.zeros(1, 2, 4, 6), torch.ones(1, 2, 4, 6), torch.full((1, 2, 4, 6), 2.0)
        for out in ({"flow_final": a, "flow_init": b}, {"flow_init": b, "flow_final": a},
                    {"flows": a[:, None], "flow_low": [b], "flow_small": c}):
            name, finest = finest_flow(collect_flows(out))
            assert torch.equal(finest, a) and "flow_init" not in name, name
        assert finest_flow(collect_flows({"flow_init": b}))[0] == "flow['flow_init']"
        # otherwise the last among equals: a list's last (RAFT's final iterate), a dict's last
        assert torch.equal(finest_flow(collect_flows([a, b, c]))[1], c)
        assert torch.equal(finest_flow(collect_flows({"flow_up": b, "flow": c}))[1], c)
        assert torch.equal(finest_flow(collect_flows({"flow_init": c, "flows": [a, b]}))[1], b)

    def test_map_keeps_containers_and_passes_other_values(self):
        occ = torch.zeros(1, 1, 4, 6)
        out = OrderedDict(flow_up=[torch.zeros(1, 2, 4, 6)], occ=occ, pair=Pair(torch.zeros(1, 2, 2, 3),
                                                                                    torch.zeros(1, 2, 4, 6)))
        mapped = map_flows(out, lambda f: f + 1, (*DEFAULT_FLOW_KEYS, "pair"))
        assert type(mapped) is OrderedDict and mapped["occ"] is occ
        assert isinstance(mapped["pair"], Pair) and float(mapped["pair"].low.min()) == 1.0
        stack = torch.zeros(2, 3, 2, 4, 6)
        assert torch.equal(map_flows(stack, lambda f: f + 1), stack + 1)

    def test_errors_name_the_place(self):
        # each message starts with the place it names (anchored: a message without it fails)
        with pytest.raises(ValueError, match=r"^flow\['flows'\]: expected at least one prediction .* N = 0"):
            collect_flows({"flows": torch.zeros(1, 0, 2, 4, 6)})
        with pytest.raises(ValueError, match=r"^flow\[1\]: expected a flow of shape .* got \(1, 3, 4, 6\)$"):
            collect_flows([torch.zeros(1, 2, 4, 6), torch.zeros(1, 3, 4, 6)])
        with pytest.raises(ValueError, match=r"^flow: expected B, H and W of at least 1, got shape \(1, 2, 0, 6\)$"):
            collect_flows(torch.zeros(1, 2, 0, 6))
        with pytest.raises(ValueError, match=r"^flow: expected a non-empty list of flows"):
            collect_flows([])
        with pytest.raises(TypeError, match=r"^flow: expected a flow tensor \(B, 2, H, W\), .* got str$"):
            collect_flows("flow")

    def test_map_errors_name_the_place(self):
        """Once an AttributeError ('int' object has no attribute 'items') from inside map_flows."""
        with pytest.raises(TypeError, match=r"^output: expected a flow tensor \(B, 2, H, W\), .* got int$"):
            map_flows(3, lambda f: f)
        with pytest.raises(TypeError, match=r"^output: expected a flow tensor .* got str$"):
            map_flows("abc", lambda f: f)
        with pytest.raises(TypeError, match=r"^output\['flows'\]\[1\]: expected a flow tensor .* got NoneType$"):
            map_flows({"flows": [torch.zeros(1, 2, 4, 6), None]}, lambda f: f)

    def test_refiner_rejects_empty_ptlflow_stack(self, scene):
        with pytest.raises(ValueError, match=r"^flow\['flows'\]: expected at least one prediction in the "
                                             r"\(B, N, 2, H, W\) stack, got N = 0 \(shape \(1, 0, 2, 53, 94\)\)$"):
            refine_flow({"flows": torch.zeros(1, 0, 2, *SIZE)}, scene["road"], scene["camera"], scene["odometry"])

    @pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                             ids=["f16-under-bf16", "bf16-under-f16"])
    def test_half_ptlflow_stack_under_autocast_of_the_other_half_dtype(self, scene, half, amp):
        """A (B, N, 2, H, W) stack held in float16 refined under bfloat16 autocast (or the
        reverse) raised torch's RuntimeError "Unexpected floating ScalarType in
        at::autocast::prioritize" when the refined predictions were stacked again (autocast's
        stack refuses the half dtype it does not cast to): it is the stack refined without
        autocast, in its own dtype, each prediction refined as alone."""
        flow, _ = displacement_flow(scene["camera"], scene["odometry"]["x_d"], scene["odometry"]["z_d"],
                                    scene["odometry"]["yaw"], SIZE)
        stack = torch.stack([flow * 0.6, flow * 0.8], dim=1).to(half)
        args = scene["road"], scene["camera"], scene["odometry"]
        reference = refine_flow({"flows": stack}, *args).flow["flows"]
        with torch.autocast("cpu", dtype=amp):
            got = refine_flow({"flows": stack}, *args).flow["flows"]
        assert got.dtype == half and torch.equal(got, reference)
        for n in range(2):
            assert torch.equal(got[:, n], refine_flow(stack[:, n], *args).flow)


# -- ptlflow inputs --------------------------------------------------------------------------------

class TestPtlflowInputs:
    def test_bgr_unit_range_and_back(self):
        g = torch.Generator().manual_seed(0)
        im1, im2 = (torch.rand(2, 3, 5, 7, generator=g) * 255 for _ in range(2))
        inputs = ptlflow_inputs(im1, im2)
        images = inputs["images"]
        assert images.shape == (2, 2, 3, 5, 7)
        # channel 0 is blue (RGB channel 2), scaled to [0, 1]
        torch.testing.assert_close(images[:, 0, 0], im1[:, 2] / 255)
        torch.testing.assert_close(images[:, 1, 2], im2[:, 0] / 255)
        back1, back2 = images_from_ptlflow(inputs)
        torch.testing.assert_close(back1, im1)
        torch.testing.assert_close(back2, im2)

    def test_errors(self):
        with pytest.raises(ValueError, match=r"inputs\['images'\]: expected shape \(B, 2, 3, H, W\)"):
            images_from_ptlflow({"images": torch.zeros(1, 3, 5, 7)})
        with pytest.raises(ValueError, match=r"expected BGR values in \[0, 1\]"):
            images_from_ptlflow({"images": torch.full((1, 2, 3, 5, 7), 255.0)})
        with pytest.raises(ValueError, match="image2: expected the shape of image1"):
            ptlflow_inputs(torch.zeros(1, 3, 5, 7), torch.zeros(1, 3, 5, 8))

    def test_images_on_two_devices_name_image2(self):
        """torch.stack raised its own RuntimeError ("Tensor on device meta is not on the expected
        device cpu!"), naming neither image; the meta device stands for another GPU or the CPU."""
        im = torch.full((1, 3, 5, 7), 128.0)
        with pytest.raises(ValueError, match=r"^image2: expected the device of image1 \(cpu\), got meta$"):
            ptlflow_inputs(im, im.to("meta"))
        with pytest.raises(ValueError, match=r"^image2: expected the device of image1 \(meta\), got cpu$"):
            ptlflow_inputs(im.to("meta"), im)

    def test_structure_errors_name_inputs(self):
        """A tensor gave an IndexError, a dict without 'images' a bare KeyError."""
        with pytest.raises(TypeError, match=r"^inputs: expected ptlflow's dict \{'images': .*\}, got Tensor$"):
            images_from_ptlflow(torch.zeros(1, 2, 3, 5, 7))
        with pytest.raises(TypeError, match=r"^inputs: expected ptlflow's dict .*, got a dict without 'images' "
                                            r"\(keys \['imgs'\]\)$"):
            images_from_ptlflow({"imgs": torch.zeros(1, 2, 3, 5, 7)})

    def test_an_overshoot_the_check_accepts_gives_a_dict_the_refiner_accepts(self, scene):
        """Images up to 1 % beyond 0..255 (a bicubic resize's overshoot) passed ptlflow_inputs'
        check and became BGR values up to 1.01, which the wrapper, the refiner's images= and the
        stand-in then refused ("expected BGR values in [0, 1]"): the dict is clipped to [0, 1]."""
        im1, im2 = scene["image1"].clone(), scene["image2"].clone()
        im1[0, 0, 3, 4], im2[0, 2, 5, 6] = 257.0, -2.0
        images = ptlflow_inputs(im1, im2)["images"]
        assert float(images.min()) == 0.0 and float(images.max()) == 1.0
        back1, back2 = images_from_ptlflow({"images": images})
        torch.testing.assert_close(back1, im1.clamp(0, 255))
        torch.testing.assert_close(back2, im2.clamp(0, 255))
        model = FreespaceRefined(PtlflowRAFTStandIn(seed=0, iters=1).eval(), FreespaceRefiner(gate=None),
                                 pad=InputPadder(8))
        with torch.no_grad():
            out = model({"images": images}, camera=scene["camera"], mask=scene["road"], odometry=scene["odometry"])
        assert out["flows"].shape == (1, 1, 2, *SIZE) and bool(torch.isfinite(out["flows"]).all())

    def test_a_multi_frame_input_is_refused_not_read_as_its_first_two_frames(self, scene):
        """ptlflow's VideoFlow takes 3 frames (B, 3, 3, H, W) and returns the flow of the middle
        frame to the last; the dict's first two frames were taken as the flow's pair, so the
        refiner fitted and gated that flow with the wrong images (here the road found in two
        identical frames: "static", left unrefined). Only a pair is taken now."""
        im1, im2 = scene["image1"], scene["image2"]
        pair = ptlflow_inputs(im1, im2)["images"]
        three = {"images": torch.cat([pair[:, :1], pair], 1)}  # frames (1, 1, 2): its flow is 1 -> 2

        class VideoFlowLike(torch.nn.Module):
            calls = 0

            def forward(self, inputs):
                VideoFlowLike.calls += 1
                return {"flows": torch.zeros(1, 1, 2, *inputs["images"].shape[-2:])}

        msg = r"^{}\['images'\]: expected shape \(B, 2, 3, H, W\) .*got \(1, 3, 3, 53, 94\): the pair of a 3-frame input"
        with pytest.raises(ValueError, match=msg.format("inputs")):
            FreespaceRefined(VideoFlowLike(), road="auto")(three, camera=scene["camera"])
        assert VideoFlowLike.calls == 0  # (refused before the network runs)
        with pytest.raises(ValueError, match=msg.format("images")):
            refine_flow(torch.zeros(1, 2, *SIZE), scene["road"], scene["camera"], images=three)
        with pytest.raises(ValueError, match=msg.format("inputs")):
            images_from_ptlflow(three)
        # the pair itself is read as it was
        back1, back2 = images_from_ptlflow({"images": pair})
        torch.testing.assert_close(back1, im1, atol=1e-4, rtol=0)
        torch.testing.assert_close(back2, im2, atol=1e-4, rtol=0)

    @pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                             ids=["f16-under-bf16", "bf16-under-f16"])
    def test_half_images_under_autocast_of_the_other_half_dtype(self, half, amp):
        """float16 images under bfloat16 autocast (or the reverse) raised torch's RuntimeError
        "Unexpected floating ScalarType in at::autocast::prioritize" from the pair's stack: the
        dict is the one without autocast, in the images' dtype."""
        g = torch.Generator().manual_seed(0)
        im1, im2 = ((torch.rand(2, 3, 5, 7, generator=g) * 255).to(half) for _ in range(2))
        with torch.autocast("cpu", dtype=amp):
            images = ptlflow_inputs(im1, im2)["images"]
        assert images.dtype == half
        assert torch.equal(images, ptlflow_inputs(im1, im2)["images"])
        assert torch.equal(images[:, 0, 0], (im1[:, 2] / 255).clamp(0, 1))

    @pytest.mark.parametrize("shape, letter", [((0, 3, 5, 6), "B"), ((1, 3, 0, 6), "H"), ((1, 3, 5, 0), "W")])
    def test_empty_images_are_refused(self, shape, letter):
        """An empty batch or side gave an empty ptlflow dict."""
        with pytest.raises(ValueError, match=rf"^image1: expected shape \(B, 3, H, W\) with {letter} >= 1, got"):
            ptlflow_inputs(torch.zeros(shape), torch.zeros(shape))


# -- padding and the camera --------------------------------------------------------------------------

class TestPadding:
    def test_raft_rules(self):
        # RAFT's KITTI padder: 375x1242 -> 376x1248, (left, right, top, bottom) = (3, 3, 0, 1)
        assert InputPadder(8, mode="kitti").padding((375, 1242)) == Padding(3, 3, 0, 1)
        assert InputPadder(8).padding(SIZE) == Padding(1, 1, 1, 2)
        assert InputPadder(8, mode="kitti").padding(SIZE) == Padding(1, 1, 0, 3)
        assert InputPadder(8).padding((48, 64)).is_zero

    def test_padding_is_raft_and_ptlflow_rule_for_every_size(self):
        """RAFT's InputPadder (core/utils/utils.py), written out: pad_ht = (((ht // s) + 1) * s - ht)
        % s; 'sintel' [pad_wd // 2, pad_wd - pad_wd // 2, pad_ht // 2, pad_ht - pad_ht // 2], else
        [pad_wd // 2, pad_wd - pad_wd // 2, 0, pad_ht] (ptlflow's with two_side_pad True / False)."""
        def raft(ht, wd, s, mode):
            pad_ht, pad_wd = (((ht // s) + 1) * s - ht) % s, (((wd // s) + 1) * s - wd) % s
            if mode == "sintel":
                return [pad_wd // 2, pad_wd - pad_wd // 2, pad_ht // 2, pad_ht - pad_ht // 2]
            return [pad_wd // 2, pad_wd - pad_wd // 2, 0, pad_ht]

        for stride in (1, 2, 7, 8, 32, 64):
            for mode in ("sintel", "kitti"):
                padder = InputPadder(stride, mode=mode)
                for ht in range(1, 70):
                    for wd in (1, 7, 8, 9, 63, 65, 1242):
                        p = padder.padding((ht, wd))
                        assert [p.left, p.right, p.top, p.bottom] == raft(ht, wd, stride, mode), (stride, mode, ht, wd)

    def test_padded_camera_sees_the_road_where_the_padding_moved_it(self):
        """Padding.camera is the camera of the padded grid, where pixel (u, v) is (u + left, v + top):
        the road flow there, cropped back, is the input grid's flow (left, top and the other two
        sides all different, as RAFT's KITTI padder's (3, 3, 0, 1))."""
        cam = Camera(torch.tensor([[90.0, 0.0, 61.0], [0.0, 88.0, 12.0], [0.0, 0.0, 1.0]], dtype=torch.float64),
                     1.65, 0.01, -0.02)
        size = (40, 120)
        flow, valid = displacement_flow(cam, 0.1, 1.1, 0.02, size)
        for p in (Padding(3, 1, 0, 2), Padding(0, 2, 5, 1), Padding(4, 0, 1, 3)):
            padded, padded_valid = displacement_flow(p.camera(cam), 0.1, 1.1, 0.02, p.padded_size(size))
            assert torch.equal(p.unpad(padded_valid), valid) and bool(valid.any())
            torch.testing.assert_close(p.unpad(padded), flow)

    def test_pad_unpad_any_leading_dims(self):
        x = torch.arange(2 * 2 * 3 * 5 * 7, dtype=torch.float32).reshape(2, 2, 3, 5, 7)
        p = Padding(1, 2, 3, 0)
        y = p.pad(x)
        assert y.shape == (2, 2, 3, 8, 10)
        assert torch.equal(p.unpad(y), x)
        assert torch.equal(y[..., 0, 0], x[..., 0, 0])  # replicated corner
        m = p.pad(torch.ones(1, 1, 5, 7, dtype=torch.bool))
        assert m.dtype == torch.bool and int(m.sum()) == 35

    @pytest.mark.parametrize("mode", ["replicate", "reflect", "constant"])
    @pytest.mark.parametrize("shape", [(2, 3, 0, 45), (2, 3, 33, 0), (0, 7)])
    def test_pad_refuses_an_image_without_pixels(self, mode, shape):
        """An image without rows or columns raised torch's RuntimeError from inside F.pad
        (replicate), or came back as a made-up image of zeros (constant)."""
        with pytest.raises(ValueError, match=rf"^x: expected an image with H, W >= 1, got shape {re.escape(str(shape))}$"):
            Padding(1, 2, 3, 4).pad(torch.zeros(shape), mode=mode)
        with pytest.raises(ValueError, match=r"^x: expected an image with H, W >= 1"):
            Padding().pad(torch.zeros(shape), mode=mode)

    def test_unpad_checks_its_input(self):
        """A tensor no larger than the padding was cropped to an empty one without a word."""
        p = Padding(1, 2, 1, 2)
        assert p.unpad(torch.zeros(1, 2, 4, 4)).shape == (1, 2, 1, 1)
        with pytest.raises(ValueError, match=r"^x: expected a padded image larger than the padding "
                                             r"Padding\(left=1, right=2, top=1, bottom=2\), got \(H, W\) = \(3, 3\)$"):
            p.unpad(torch.zeros(1, 2, 3, 3))
        with pytest.raises(ValueError, match=r"^x: expected a padded image larger .* got \(H, W\) = \(5, 3\)$"):
            p.unpad(torch.zeros(5, 3))
        with pytest.raises(ValueError, match=r"^x: expected at least 2 dimensions \(..., H, W\), got shape \(5,\)$"):
            p.unpad(torch.zeros(5))
        with pytest.raises(TypeError, match=r"^x: expected a tensor \(..., H, W\), got ndarray$"):
            p.unpad(np.zeros((13, 21)))

    def test_numpy_integers_are_ints(self):
        """Padding(np.int64(1)) and InputPadder(np.int64(8)) were refused; a bool is not an int."""
        p = Padding(np.int64(1), np.int32(2), np.uint8(0), 3)
        assert p == Padding(1, 2, 0, 3) and all(type(v) is int for v in (p.left, p.right, p.top, p.bottom))
        padder = InputPadder(np.int64(8), mode="kitti")
        assert padder.stride == 8 and type(padder.stride) is int
        assert padder.padding((375, 1242)) == Padding(3, 3, 0, 1)
        with pytest.raises(TypeError, match=r"^left: expected an int, got bool True$"):
            Padding(True)
        with pytest.raises(ValueError, match=r"^bottom: expected an int >= 0, got -1$"):
            Padding(0, 0, 0, -1)
        with pytest.raises(TypeError, match=r"^stride: expected an int, got bool True$"):
            InputPadder(True)
        with pytest.raises(TypeError, match=r"^stride: expected an int, got float 8.0$"):
            InputPadder(8.0)

    def test_camera_follows_padding(self, kitti_K):
        """The model flow of the padded camera on the padded grid is the original one, shifted."""
        cam = Camera(kitti_K, 1.65, 0.01, -0.02)
        H, W = 60, 100
        cam = cam.scaled(W / 1242, H / 375)
        left, top, right, bottom = 3, 2, 5, 1
        padded = cam.padded(left, top, right, bottom)
        expected_K = cam.K.clone()
        expected_K[:, 0, 2] += left
        expected_K[:, 1, 2] += top
        torch.testing.assert_close(padded.K, expected_K, rtol=0, atol=1e-12)
        f0, v0 = displacement_flow(cam, 0.1, 1.2, 0.02, (H, W))
        f1, v1 = displacement_flow(padded, 0.1, 1.2, 0.02, (H + top + bottom, W + left + right))
        crop = (..., slice(top, top + H), slice(left, left + W))
        assert torch.equal(v1[crop], v0)
        torch.testing.assert_close(f1[crop], f0, rtol=0, atol=1e-9)
        back = padded.cropped(left, top, right, bottom)
        torch.testing.assert_close(back.K, cam.K, rtol=0, atol=1e-12)
        assert cam.padded(0, 0) is cam

    @pytest.mark.parametrize("bad, err", [(-1, ValueError), (1.5, TypeError), (True, TypeError)])
    def test_camera_padding_errors(self, kitti_K, bad, err):
        with pytest.raises(err, match="left: expected"):
            Camera(kitti_K, 1.65).padded(bad, 0)
        with pytest.raises(err, match="left: expected"):
            Camera(kitti_K, 1.65).cropped(bad, 0)


# -- the stand-ins reproduce the contracts ----------------------------------------------------------

class TestStandIns:
    def test_ptlflow_shapes(self, scene):
        net = PtlflowRAFTStandIn(iters=2).eval()
        with torch.no_grad():
            out = net(ptlflow_inputs(scene["image1"], scene["image2"]))
        assert set(out) == {"flows", "flow_small"}
        assert out["flows"].shape == (1, 1, 2, *SIZE)
        assert out["flow_small"].shape == (1, 2, 56 // 8, 96 // 8)  # 1/8 of the padded 56x96
        with pytest.raises(ValueError, match=r"\[0, 1\]"):  # 0..255 RGB is not ptlflow's convention
            net({"images": torch.stack([scene["image1"], scene["image2"]], 1)})

    def test_ptlflow_colour_order_matters(self, scene):
        net = PtlflowRAFTStandIn(iters=2).eval()
        inputs = ptlflow_inputs(scene["image1"], scene["image2"])
        swapped = {"images": inputs["images"].flip(2)}  # RGB where BGR is expected
        with torch.no_grad():
            assert not torch.equal(net(inputs)["flows"], net(swapped)["flows"])

    def test_torchvision_needs_divisible_sizes(self, scene):
        net = TorchvisionRAFTStandIn().eval()
        x = scene["image1"] / 127.5 - 1
        with pytest.raises(ValueError, match="divisible by 8, instead got 53 .h. and 94 .w."):
            net(x, x)
        with torch.no_grad():
            flows = net(F.pad(x, (1, 1, 1, 2)), F.pad(x, (1, 1, 1, 2)), num_flow_updates=3)
        assert isinstance(flows, list) and len(flows) == 3 and flows[-1].shape == (1, 2, 56, 96)


# -- the wrapper on the padded grid -----------------------------------------------------------------

class TestFreespaceRefinedContracts:
    def test_ptlflow_dict_in_and_out(self, scene):
        net = PtlflowRAFTStandIn(iters=2).eval()
        model = FreespaceRefined(net, FreespaceRefiner(fit="flow", gate=None), pad=InputPadder(8))
        inputs = ptlflow_inputs(scene["image1"], scene["image2"])
        cam, road, odo = scene["camera"], scene["road"], scene["odometry"]
        with torch.no_grad():
            raw = net(inputs)  # the net pads internally
            out, info = model(inputs, mask=road, camera=cam, odometry=odo, return_info=True)
        assert set(out) == {"flows", "flow_small"} and out["flows"].shape == raw["flows"].shape
        assert out["flow_small"].shape == raw["flow_small"].shape
        # full size: the refinement of the unpadded flow with the unpadded camera
        expected = refine_flow(raw["flows"][:, 0], road, cam, odo).flow
        _assert_refined(out["flows"][:, 0], raw["flows"][:, 0], expected, road)
        # flow_small: the model flow of the padded camera scaled to 1/8, inside the mask padded
        # and reduced to the 1/8 pixels whose 8x8 footprint is all road
        pad = Padding(1, 1, 1, 2)
        K = cam.K.clone()
        K[:, 0, 0] /= 8
        K[:, 1, 1] /= 8
        K[:, 0, 2] = (K[:, 0, 2] + pad.left + 0.5) / 8 - 0.5
        K[:, 1, 2] = (K[:, 1, 2] + pad.top + 0.5) / 8 - 0.5
        small_size = tuple(raw["flow_small"].shape[-2:])
        model_small, valid = displacement_flow(Camera(K, cam.height, cam.roll, cam.pitch), odo["x_d"],
                                               odo["z_d"], odo["yaw"], small_size)
        footprint = F.avg_pool2d(F.pad(road.float(), (1, 1, 1, 2)), 8) == 1.0
        _assert_refined(out["flow_small"], raw["flow_small"], model_small, footprint & valid)
        # the info is given at the input size, with the input's camera
        assert info.mask.shape == (1, 1, *SIZE) and info.weight.shape == (1, 1, *SIZE)
        torch.testing.assert_close(info.camera.K, cam.K, rtol=0, atol=1e-5)
        assert torch.equal(info.mask, info.mask & road)

    def test_torchvision_list(self, scene):
        net = TorchvisionRAFTStandIn().eval()
        model = FreespaceRefined(net, FreespaceRefiner(fit="flow", gate=None), pad=InputPadder(8), image_range=(-1.0, 1.0))
        x1, x2 = scene["image1"] / 127.5 - 1, scene["image2"] / 127.5 - 1
        cam, road, odo = scene["camera"], scene["road"], scene["odometry"]
        pad = Padding(1, 1, 1, 2)
        with torch.no_grad():
            raw = [pad.unpad(f) for f in net(pad.pad(x1), pad.pad(x2), num_flow_updates=3)]
            out = model(x1, x2, mask=road, camera=cam, odometry=odo, num_flow_updates=3)
        assert isinstance(out, list) and len(out) == 3
        for r, o in zip(raw, out):
            assert o.shape == (1, 2, *SIZE)
            _assert_refined(o, r, refine_flow(r, road, cam, odo).flow, road)

    def test_refiner_takes_ptlflow_input_dict_for_the_image_fit(self, scene):
        """images= may be ptlflow's input dict: the same result as the RGB 0..255 pair."""
        road, cam = scene["road"], scene["camera"]
        flow = displacement_flow(cam, scene["odometry"]["x_d"], scene["odometry"]["z_d"],
                                 scene["odometry"]["yaw"], SIZE)[0]
        refiner = FreespaceRefiner(fit="photometric", warn=False)
        pair = (scene["image1"], scene["image2"])
        a = refiner(flow, road, cam, images=pair)
        b = refiner(flow, road, cam, images=ptlflow_inputs(*pair))
        for k in ("x_d", "z_d", "yaw"):
            torch.testing.assert_close(a.odometry[k], b.odometry[k], rtol=1e-5, atol=1e-6)

    def test_wrapper_errors(self, scene):
        net = TorchvisionRAFTStandIn().eval()
        with pytest.raises(TypeError, match="pad: expected an InputPadder"):
            FreespaceRefined(net, pad=8)
        with pytest.raises(ValueError, match="image_range"):
            FreespaceRefined(net, image_range=(1.0, 1.0))
        model = FreespaceRefined(net, pad=InputPadder(8))
        with pytest.raises(TypeError, match="inputs: expected"):
            model(scene["image1"], camera=scene["camera"], mask=scene["road"])
        with pytest.raises(ValueError, match=r"^mask: expected shape \(1, 1, 53, 94\) \(the images' batch and size"):
            x = scene["image1"] / 127.5 - 1
            model(x, x, camera=scene["camera"], mask=scene["road"][..., :-1])
        # the camera is checked before the padding moves it; a bad range or road option is named
        # when the wrapper is built, not after the network ran
        for camera in (None, scene["camera"].K):
            with pytest.raises(TypeError, match=r"^camera: expected a fsof_torch.Camera, got"):
                model(x, x, camera=camera, mask=scene["road"])
        for bad in ((0,), "ab", None, (0, True)):
            with pytest.raises(TypeError, match=r"^image_range: expected \(low, high\), two numbers"):
                FreespaceRefined(net, image_range=bad)
        with pytest.raises(TypeError, match=r"^road_options: unknown options \['bogus'\] of detect_road"):
            FreespaceRefined(net, road="auto", road_options={"bogus": 1})

    def test_padded_info_maps_are_at_the_input_size(self, scene):
        """With the padding, every map of the returned info (the gate's and the found road's too)
        comes at the input size, as the refined flow does."""
        net = TorchvisionRAFTStandIn().eval()
        model = FreespaceRefined(net, road="auto", pad=InputPadder(8), image_range=(-1.0, 1.0))
        x1, x2 = scene["image1"] / 127.5 - 1, scene["image2"] / 127.5 - 1
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            _, info = model(x1, x2, camera=scene["camera"], num_flow_updates=3, return_info=True)
        assert info.gate is not None and info.road is not None
        for name, t in (("gate.use_model", info.gate.use_model), ("gate.evidence", info.gate.evidence),
                        ("road.mask", info.road.mask), ("road.seed", info.road.seed), ("mask", info.mask)):
            assert tuple(t.shape[-2:]) == SIZE, name
