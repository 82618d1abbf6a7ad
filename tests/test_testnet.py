"""Tests of the RAFT-style test net: shapes, any size, seeding, state_dict, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fsof_torch.training.testnet import TinyRAFT, count_parameters


def _pair(B: int, H: int, W: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    image1 = torch.rand(B, 3, H, W, generator=g) * 255
    image2 = torch.roll(image1, shifts=(0, 2), dims=(2, 3))
    return image1, image2


# -- smoke ---------------------------------------------------------------------------------------

def test_forward_backward_kitti_like_size():
    """The issue's case: a 1x3x128x416 pair, forward and backward on the CPU."""
    net = TinyRAFT(seed=0, iters=3)
    image1, image2 = _pair(1, 128, 416)
    flows = net(image1, image2)
    assert len(flows) == 3
    assert all(f.shape == (1, 2, 128, 416) for f in flows)
    loss = sum(f.abs().mean() for f in flows)
    loss.backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_parameter_count_small():
    assert count_parameters(TinyRAFT()) < 500_000


# -- cardinality ---------------------------------------------------------------------------------

@pytest.mark.parametrize("B,H,W", [(1, 37, 61), (3, 40, 72), (2, 9, 13), (2, 8, 8), (1, 1, 1), (1, 3, 8)])
@pytest.mark.parametrize("training", [False, True])
def test_any_size_and_batch(B, H, W, training):
    """Images of at most 8 x 8 pixels too (one feature pixel, which instance norm refuses, unless widened)."""
    net = TinyRAFT(seed=1, iters=2).train(training)
    image1, image2 = _pair(B, H, W)
    with torch.no_grad():
        flows = net(image1, image2)
    assert [tuple(f.shape) for f in flows] == [(B, 2, H, W)] * 2
    assert all(torch.isfinite(f).all() for f in flows)


def test_iters_override():
    net = TinyRAFT(seed=0, iters=4)
    image1, image2 = _pair(1, 32, 48)
    with torch.no_grad():
        assert len(net(image1, image2, iters=2)) == 2
        assert len(net(image1, image2)) == 4


@pytest.mark.parametrize("B,H,W,iters", [(2, 40, 56, 3), (1, 37, 61, 1), (1, 9, 13, 2)])
def test_final_only_is_the_last_flow(B, H, W, iters):
    """final_only (RAFT's test mode) returns the very flow that is last in the full list, bit for
    bit, and the same gradients flow from it into the weights."""
    net = TinyRAFT(seed=0, iters=iters).eval()
    image1, image2 = _pair(B, H, W)
    with torch.no_grad():
        full = net(image1, image2)
        final = net(image1, image2, final_only=True)
    assert len(full) == iters and len(final) == 1 and torch.equal(final[0], full[-1])
    grads = []
    for kwargs in ({}, {"final_only": True}):
        net.zero_grad()
        net(image1, image2, **kwargs)[-1].square().mean().backward()
        grads.append({n: p.grad.clone() for n, p in net.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and all(torch.equal(grads[0][n], grads[1][n]) for n in grads[0])


def test_final_only_checked():
    net = TinyRAFT(seed=0, iters=2)
    image1, image2 = _pair(1, 16, 16)
    with pytest.raises(TypeError, match="final_only: expected a bool, got int"):
        net(image1, image2, final_only=1)


def test_batch_elements_independent():
    """Instance norm and padding act per image: a sample's flow does not depend on its batch mates."""
    net = TinyRAFT(seed=0, iters=2).eval()
    image1, image2 = _pair(3, 24, 40)
    with torch.no_grad():
        batched = net(image1, image2)[-1]
        single = net(image1[1:2], image2[1:2])[-1]
    torch.testing.assert_close(batched[1:2], single, atol=1e-4, rtol=1e-4)


# -- seeding and state ---------------------------------------------------------------------------

def test_same_seed_same_weights_and_rng_untouched():
    state = torch.get_rng_state()
    a, b, c = TinyRAFT(seed=3), TinyRAFT(seed=3), TinyRAFT(seed=4)
    assert torch.equal(state, torch.get_rng_state())
    for (name, pa), pb, pc in zip(a.state_dict().items(), b.state_dict().values(), c.state_dict().values()):
        assert torch.equal(pa, pb), name
    assert any(not torch.equal(pa, pc) for pa, pc in zip(a.state_dict().values(), c.state_dict().values()))


def test_seeded_weights_of_concurrent_builds():
    """Nets built in several threads at once, while another thread draws from the global random
    state, are those a lone build gives; and that thread's numbers are its own seed's."""
    from concurrent.futures import ThreadPoolExecutor

    lone = {s: TinyRAFT(seed=s, iters=1, feature_dim=8, hidden_dim=8, context_dim=8).state_dict() for s in range(4)}

    def build(s):
        return TinyRAFT(seed=s, iters=1, feature_dim=8, hidden_dim=8, context_dim=8).state_dict()

    def draw():
        torch.manual_seed(123)
        return [torch.rand(100) for _ in range(300)]

    with torch.random.fork_rng(devices=[]):  # (the global state as it was, after the test)
        expected = draw()
        for _ in range(3):
            with ThreadPoolExecutor(5) as pool:
                drawn = pool.submit(draw)
                built = {s: pool.submit(build, s) for s in range(4)}
                for s, future in built.items():
                    state = future.result()
                    assert all(torch.equal(state[k], lone[s][k]) for k in state), s
                assert all(torch.equal(a, b) for a, b in zip(drawn.result(), expected))


def test_a_build_seeds_no_accelerator(monkeypatch):
    """The seed stays with the net: no device's global generator is seeded (torch.manual_seed
    would seed every CUDA device's too)."""
    seeded = []
    monkeypatch.setattr(torch.cuda, "manual_seed_all", lambda seed: seeded.append(seed))
    monkeypatch.setattr(torch.cuda, "manual_seed", lambda seed: seeded.append(seed))
    state = torch.get_rng_state()
    TinyRAFT(seed=7, iters=1)
    assert seeded == [] and torch.equal(state, torch.get_rng_state())


def test_weights_are_torchs_default_initialisation():
    """The weights are the default initialisation of torch's layers drawn from the seed in the
    order they are built (the same numbers as ``torch.manual_seed(seed)`` and building the net)."""
    import torch.nn as nn

    net = TinyRAFT(seed=11, iters=1)
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(11)
        again = [nn.Conv2d(m.in_channels, m.out_channels, m.kernel_size, stride=m.stride, padding=m.padding)
                 for m in convs]
    for i, (a, b) in enumerate(zip(convs, again)):
        assert torch.equal(a.weight, b.weight) and torch.equal(a.bias, b.bias), i


def test_state_dict_round_trip(tmp_path):
    a = TinyRAFT(seed=5, iters=2)
    torch.save(a.state_dict(), tmp_path / "net.pt")
    b = TinyRAFT(seed=6, iters=2)
    b.load_state_dict(torch.load(tmp_path / "net.pt"))
    image1, image2 = _pair(1, 24, 40)
    with torch.no_grad():
        torch.testing.assert_close(a(image1, image2)[-1], b(image1, image2)[-1], atol=0, rtol=0)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bf16", "f16"])
def test_a_net_held_in_half_precision_looks_up_at_float32_positions(monkeypatch, dtype):
    """A net held in bfloat16 built its coordinates and accumulated its flow in bfloat16: past 128
    feature pixels (1024 px) every lookup position was a whole feature pixel (8 px). They are
    float32, as RAFT's coordinates (and as under autocast); the flows come back in the net's dtype."""
    import fsof_torch.training.testnet as testnet

    seen = []
    lookup = testnet._lookup

    def spy(pyramid, coords, radius):
        far = coords[:, 0, :, 130:]
        seen.append((coords.dtype, pyramid[0].dtype, float((far - far.round()).abs().amax())))
        return lookup(pyramid, coords, radius)

    monkeypatch.setattr(testnet, "_lookup", spy)
    net = TinyRAFT(seed=0, iters=2).to(dtype)
    image1, image2 = _pair(1, 16, 1088)
    with torch.no_grad():
        flows = net(image1.to(dtype), image2.to(dtype))
    assert [dtypes for *dtypes, _ in seen] == [[torch.float32, torch.float32]] * 2
    assert seen[1][2] > 0.01  # the second lookup's positions keep the first update's fractions
    assert [f.dtype for f in flows] == [dtype, dtype]


@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-under-bf16", "bf16-under-f16"])
def test_half_images_under_autocast_of_the_other_half_dtype(half, amp):
    """float16 frames into a float32 net under bfloat16 autocast (or the reverse) raised torch's
    RuntimeError "Unexpected floating ScalarType in at::autocast::prioritize" (autocast's stack
    and cat refuse the half dtype they do not cast to): the flows are those of the frames lifted
    to float32 under the same autocast."""
    net = TinyRAFT(seed=0, iters=2)
    image1, image2 = _pair(1, 24, 40)
    image1, image2 = image1.to(half), image2.to(half)
    with torch.no_grad(), torch.autocast("cpu", dtype=amp):
        got = net(image1, image2)
        ref = net(image1.float(), image2.float())
    assert [f.dtype for f in got] == [torch.float32] * 2
    for g, r in zip(got, ref):
        torch.testing.assert_close(g, r, rtol=0, atol=0)



@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-net-under-bf16", "bf16-net-under-f16"])
def test_a_net_held_in_half_precision_under_autocast_of_the_other_half_dtype(half, amp):
    """A net held in float16 under bfloat16 autocast (or the reverse) raised torch's RuntimeError
    "Unexpected floating ScalarType in at::autocast::prioritize" from the concatenation of the two
    frames cast to the net's dtype, whatever the frames' dtype: it runs, and its flows are those of
    the same weights held in float32 under the same autocast (autocast casts both to its dtype)
    up to the frames' rounding to the net's dtype before the first convolution."""
    image1, image2 = _pair(1, 24, 40)
    net = TinyRAFT(seed=0, iters=2).to(half)
    wide = TinyRAFT(seed=0, iters=2).to(half).float()
    with torch.no_grad(), torch.autocast("cpu", dtype=amp):
        for frames in ((image1, image2), (image1.to(half), image2.to(half))):
            got = net(*frames)
            ref = wide(image1, image2)
            assert [f.dtype for f in got] == [torch.float32] * 2  # (autocast's replicate padding is float32)
            for g, r in zip(got, ref):
                assert bool(torch.isfinite(g).all())
                torch.testing.assert_close(g, r, rtol=0, atol=1e-2)

# -- exceptions ----------------------------------------------------------------------------------

def test_rejects_bad_inputs():
    net = TinyRAFT(iters=1)
    image1, image2 = _pair(1, 16, 16)
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, 3, H, W\)"):
        net(image1[:, :1], image2)
    with pytest.raises(ValueError, match=r"image2: expected shape .*H=16"):
        net(image1, image2[..., :8, :])
    with pytest.raises(TypeError, match="image1: expected a floating-point tensor"):
        net(image1.to(torch.uint8), image2)
    with pytest.raises(ValueError, match=r"expected values on 0\.\.255"):
        net(image1 * 2, image2)
    with pytest.raises(ValueError, match="iters: expected an int >= 1, got 0"):
        net(image1, image2, iters=0)
    with pytest.raises(ValueError, match="corr_radius: expected an int >= 1, got 0"):
        TinyRAFT(corr_radius=0)
    with pytest.raises(TypeError, match="iters: expected an int, got bool True"):
        net(image1, image2, iters=True)
    with pytest.raises(TypeError, match="feature_dim: expected an int, got float 32.0"):
        TinyRAFT(feature_dim=32.0)
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, 3, H, W\) with B >= 1, got \(0, 3, 16, 16\)"):
        net(image1[:0], image2[:0])
    # a float seed is not rounded to another net's, and a string is named
    with pytest.raises(TypeError, match="seed: expected an int, got float 1.5"):
        TinyRAFT(seed=1.5)
    with pytest.raises(TypeError, match="seed: expected an int, got str 'a'"):
        TinyRAFT(seed="a")


def test_a_0_to_1_image_is_refused_as_the_library_refuses_one():
    """Images on 0..1 (torchvision's ``ToTensor``) ran through the net as near-black frames and
    gave a flow without a word, where every other image-taking call of the library refuses a
    sample whose values all lie in [0, 1] (docs/conventions.md); each sample is judged alone,
    and ``trust_image_range`` lets a frame that dark through."""
    import fsof_torch

    net = TinyRAFT(iters=1).eval()
    image1, image2 = _pair(2, 16, 16)
    with pytest.raises(ValueError, match=r"^image1: values in \[.*\] look like 0\.\.1 images, expected 0\.\.255"):
        net(image1 / 255, image2 / 255)
    dim = torch.cat([image2[:1], image2[1:] / 255])
    with pytest.raises(ValueError, match=r"^image2\[1\]: values in \[.*\] look like 0\.\.1 images"):
        net(image1, dim)
    with torch.no_grad(), fsof_torch.trust_image_range():
        flows = net(image1, dim)
    assert len(flows) == 1 and flows[0].shape == (2, 2, 16, 16) and bool(flows[0].isfinite().all())


def test_correlation_volume_is_rafts():
    """All-pairs correlation <f1(p), f2(q)> / sqrt(D), written out per pixel pair, and the
    average-pooled levels of the pyramid."""
    from fsof_torch.training.testnet import _correlation_pyramid

    g = torch.Generator().manual_seed(3)
    f1, f2 = torch.randn(2, 16, 4, 6, generator=g, dtype=torch.float64), torch.randn(2, 16, 4, 6, generator=g,
                                                                                    dtype=torch.float64)
    pyramid = _correlation_pyramid(f1, f2, 2)
    ref = torch.empty(2, 4, 6, 4, 6, dtype=torch.float64)
    for b in range(2):
        for y in range(4):
            for x in range(6):
                ref[b, y, x] = (f1[b, :, y, x, None, None] * f2[b]).sum(0) / 4.0
    torch.testing.assert_close(pyramid[0].reshape(2, 4, 6, 4, 6), ref)
    torch.testing.assert_close(pyramid[1].reshape(2, 4, 6, 2, 3),
                               ref.reshape(2, 4, 6, 2, 2, 3, 2).mean(dim=(4, 6)))


def _volume_values(H, W):
    """n (n + n1 + n2): the documented size of the volume and its two pooled levels (docs/training.md)."""
    h, w = -(-H // 8), -(-W // 8)
    return h * w * (h * w + (h // 2) * (w // 2) + (h // 4) * (w // 4))


@pytest.mark.parametrize("H, W", [(100, 130), (61, 203)])
def test_correlation_memory_is_as_documented(monkeypatch, H, W):
    """The volume the net builds holds the values docs/training.md counts (its memory grows with
    the square of the pixel count), and the figures given there follow: 0.28 GB at 375x1242, 5.5
    GB at 1080x1920, 88 GB at 2160x3840 in float32."""
    import fsof_torch.training.testnet as testnet

    built = []
    pyramid = testnet._correlation_pyramid

    def spy(f1, f2, levels):
        out = pyramid(f1, f2, levels)
        built.append(sum(level.numel() for level in out))
        return out

    monkeypatch.setattr(testnet, "_correlation_pyramid", spy)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        TinyRAFT(iters=1)(torch.rand(2, 3, H, W, generator=g) * 255, torch.rand(2, 3, H, W, generator=g) * 255)
    assert built == [2 * _volume_values(H, W)]
    assert [round(4 * _volume_values(H, W) / 1e9, 2) for H, W in ((375, 1242), (1080, 1920), (2160, 3840))] == \
        [0.28, 5.5, 88.15]


def test_numpy_integers_are_accepted_as_ints():
    """np.int64 (from np.arange, a config array) was refused for iters and the sizes; the value
    passed on is a Python int and the net is the one the same ints give."""
    net = TinyRAFT(seed=0, iters=np.int64(2), feature_dim=np.int64(32), corr_radius=np.int32(2))
    ref = TinyRAFT(seed=0, iters=2, feature_dim=32, corr_radius=2)
    assert type(net.iters) is int and net.iters == 2 and type(net.corr_radius) is int
    image1, image2 = _pair(1, 16, 16)
    with torch.no_grad():
        flows = net(image1, image2, iters=np.int64(3))
        expected = ref(image1, image2, iters=3)
    assert len(flows) == 3
    assert torch.equal(flows[-1], expected[-1])
