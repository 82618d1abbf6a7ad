"""A small RAFT-style flow network to run and train when no trained weights are at hand.

``TinyRAFT`` follows RAFT (Teed & Deng, ECCV 2020) in miniature: a feature encoder and a context
encoder at 1/8 resolution, an all-pairs correlation volume with a pyramid looked up around the
current estimate, a convolutional GRU that refines the flow a few times, and convex upsampling to
full resolution after every iteration. About 0.4 M parameters, so it trains on a CPU in minutes
(on small images); it is a test net, not a competitive one.

Convention: images (B, 3, H, W) RGB on 0..255 (normalised inside); flow (B, 2, H, W) in pixels,
channel 0 = u, forward from ``image1`` to ``image2``. Any H, W: the net pads to a multiple of 8
(replicating the border; at most 8 x 8 pixels to 8 x 16, since instance norm needs two feature
pixels) and crops its outputs back. The all-pairs volume and its pooled levels hold about
1.3 (H W / 64)² float32 values a sample (0.28 GB at 375x1242, 5.5 GB at 1080x1920, 88 GB at
2160x3840): resize larger frames before running it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import autocast_off, check_float_tensor, check_image_range, check_int, check_same_device, check_shape, skip_values

__all__ = ["TinyRAFT", "count_parameters"]

STRIDE = 8  # resolution of the encoders; the all-pairs volume grows with (H W / STRIDE²)²


def count_parameters(module: nn.Module) -> int:
    """The number of trainable scalars of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def _conv(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2)


class _ResidualBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, norm: bool) -> None:
        super().__init__()
        self.conv1 = _conv(cin, cout, 3, stride)
        self.conv2 = _conv(cout, cout, 3)
        # Instance norm for the matching features (as RAFT's fnet): invariant to the brightness
        # and contrast of each image; the context encoder keeps no normalisation (RAFT-small).
        self.norm1 = nn.InstanceNorm2d(cout) if norm else nn.Identity()
        self.norm2 = nn.InstanceNorm2d(cout) if norm else nn.Identity()
        self.skip = (nn.Identity() if stride == 1 and cin == cout else
                     nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride),
                                   nn.InstanceNorm2d(cout) if norm else nn.Identity()))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        return F.relu(self.skip(x) + y)


class _Encoder(nn.Module):
    """Image (N, 3, H, W) in -1..1 -> features (N, out_dim, H/8, W/8)."""

    def __init__(self, out_dim: int, norm: bool, widths: tuple[int, int, int] = (24, 32, 48)) -> None:
        super().__init__()
        w1, w2, w3 = widths
        self.stem = nn.Sequential(_conv(3, w1, 7, 2), nn.InstanceNorm2d(w1) if norm else nn.Identity(),
                                  nn.ReLU())
        self.layer2 = _ResidualBlock(w1, w2, 2, norm)
        self.layer3 = _ResidualBlock(w2, w3, 2, norm)
        self.out = nn.Conv2d(w3, out_dim, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.out(self.layer3(self.layer2(self.stem(x))))


class _ConvGRU(nn.Module):
    def __init__(self, hidden_dim: int, input_dim: int) -> None:
        super().__init__()
        self.convz = _conv(hidden_dim + input_dim, hidden_dim)
        self.convr = _conv(hidden_dim + input_dim, hidden_dim)
        self.convq = _conv(hidden_dim + input_dim, hidden_dim)

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(self.convz(hx))
        r = torch.sigmoid(self.convr(hx))
        q = torch.tanh(self.convq(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q


class _UpdateBlock(nn.Module):
    """Correlation + flow + context -> new hidden state and flow increment; upsampling weights
    from a hidden state (:meth:`mask`, needed only for the flows that are upsampled)."""

    def __init__(self, corr_planes: int, hidden_dim: int, context_dim: int, motion_dim: int = 64) -> None:
        super().__init__()
        self.convc = nn.Conv2d(corr_planes, 64, 1)
        self.convf1 = _conv(2, 32, 7)
        self.convf2 = _conv(32, 16, 3)
        self.convm = _conv(64 + 16, motion_dim - 2)
        self.gru = _ConvGRU(hidden_dim, context_dim + motion_dim)
        self.flow_head = nn.Sequential(_conv(hidden_dim, 64), nn.ReLU(), _conv(64, 2))
        self.mask_head = nn.Sequential(_conv(hidden_dim, 64), nn.ReLU(), nn.Conv2d(64, 9 * STRIDE**2, 1))

    def forward(self, hidden: Tensor, context: Tensor, corr: Tensor, flow: Tensor) -> tuple[Tensor, Tensor]:
        c = F.relu(self.convc(corr))
        f = F.relu(self.convf2(F.relu(self.convf1(flow))))
        motion = torch.cat([F.relu(self.convm(torch.cat([c, f], dim=1))), flow], dim=1)
        hidden = self.gru(hidden, torch.cat([context, motion], dim=1))
        return hidden, self.flow_head(hidden)

    def mask(self, hidden: Tensor) -> Tensor:
        """Convex upsampling weights (logits, (B, 9 STRIDE², h, w)) from a hidden state."""
        # RAFT scales the mask logits by 1/4 to balance their gradients against the flow head's.
        return 0.25 * self.mask_head(hidden)


def _correlation_pyramid(fmap1: Tensor, fmap2: Tensor, levels: int) -> list[Tensor]:
    """All-pairs correlation (B h w, 1, h, w) and its average-pooled coarser levels.

    RAFT pools the (h w)² volume level by level; pooling is linear, so each level is computed
    instead from the pooled second feature map, ``<f1(p), mean f2(block)>`` (RAFT's alternate
    correlation does the same): a product a quarter of the previous one's size, and no pass over
    the full volume (215 MB at 375x1242). RAFT divides by sqrt(D); the features are scaled
    instead, for the same reason.
    """
    B, D, h, w = fmap1.shape
    f1 = fmap1.flatten(2).transpose(1, 2) * D**-0.5  # (B, h w, D)
    pyramid = []
    f2 = fmap2
    for level in range(levels):
        if level > 0:
            if min(f2.shape[-2:]) < 2:  # tiny images: repeat the coarsest level instead of pooling to 0
                pyramid.append(pyramid[-1])
                continue
            f2 = F.avg_pool2d(f2, 2, stride=2)
        hl, wl = f2.shape[-2:]
        corr = torch.bmm(f1, f2.flatten(2))  # (B, h w, hl wl)
        pyramid.append(corr.reshape(B * h * w, 1, hl, wl))
    return pyramid


def _lookup(pyramid: list[Tensor], coords: Tensor, radius: int) -> Tensor:
    """Bilinear samples of every level in a (2r+1)² window around ``coords`` (B, 2, h, w), x first.

    As RAFT's lookup, the window of a level pooled k times is centred on ``coords / 2**k`` (a
    level repeated for a tiny image keeps the pooling of the one it repeats). Returns
    (B, levels (2r+1)², h, w); windows reaching outside the volume read zeros.
    """
    B, _, h, w = coords.shape
    d = torch.arange(-radius, radius + 1, dtype=coords.dtype, device=coords.device)
    # delta[..., 0] is the x offset, delta[..., 1] the y offset of each window cell
    delta = torch.stack(torch.meshgrid(d, d, indexing="xy"), dim=-1).reshape(1, 2 * radius + 1, 2 * radius + 1, 2)
    centre = coords.permute(0, 2, 3, 1).reshape(B * h * w, 1, 1, 2)
    out = []
    pooled = 0
    for level, corr in enumerate(pyramid):
        if level > 0 and corr.shape[-2:] != pyramid[level - 1].shape[-2:]:
            pooled += 1  # every pooling halves both sides (floor), so a pooled level changes shape
        pts = centre / 2**pooled + delta  # pixel positions at this level
        hl, wl = corr.shape[-2:]
        if hl == 1 or wl == 1:
            # align_corners=True puts every sample of a one-pixel side on that pixel; a zero border
            # makes the window read zeros outside it, as elsewhere
            px, py = int(wl == 1), int(hl == 1)
            corr = F.pad(corr, (px, px, py, py))
            pts = pts + torch.tensor([px, py], dtype=coords.dtype, device=coords.device)
            hl, wl = corr.shape[-2:]
        scale = torch.tensor([wl - 1, hl - 1], dtype=coords.dtype, device=coords.device)
        grid = 2 * pts / scale - 1
        sampled = F.grid_sample(corr, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        out.append(sampled.reshape(B, h, w, -1))
    return torch.cat(out, dim=-1).permute(0, 3, 1, 2)


def _convex_upsample(flow: Tensor, mask: Tensor) -> Tensor:
    """Flow (B, 2, h, w) at 1/8 -> (B, 2, 8h, 8w): each fine pixel a convex mix of 3x3 coarse ones."""
    B, _, h, w = flow.shape
    mask = torch.softmax(mask.reshape(B, 1, 9, STRIDE, STRIDE, h, w), dim=2)
    nb = F.unfold(STRIDE * flow, (3, 3), padding=1).reshape(B, 2, 9, 1, 1, h, w)
    up = (mask * nb).sum(dim=2)  # (B, 2, 8, 8, h, w)
    return up.permute(0, 1, 4, 2, 5, 3).reshape(B, 2, STRIDE * h, STRIDE * w)


class TinyRAFT(nn.Module):
    """A miniature RAFT: list of full-resolution flows, one per refinement iteration.

    Args:
        seed: an int with 0 <= seed < 2**64; the weights are torch's default initialisation drawn
            from a generator of the net's own seeded with it (the numbers ``torch.manual_seed(seed)``
            and a build would draw), so the same seed gives the same net, also built in several
            threads at once, and no global random state (CPU or CUDA) is read or changed.
        iters: default number of GRU iterations (the length of the returned list).
        feature_dim: channels of the matching features.
        hidden_dim, context_dim: channels of the GRU state and of the context features.
        corr_levels, corr_radius: correlation pyramid depth and lookup radius (in 1/8 pixels per
            level); the reach is about ``8 · corr_radius · 2^(corr_levels-1)`` pixels per iteration.

    ``iters`` and the sizes are ints >= 1 (NumPy integers too; a bool or a float raises TypeError).

    Example:
        >>> net = TinyRAFT(seed=0, iters=4)
        >>> flows = net(torch.rand(1, 3, 64, 100) * 255, torch.rand(1, 3, 64, 100) * 255)
        >>> len(flows), flows[-1].shape
        (4, torch.Size([1, 2, 64, 100]))
    """

    flow_contract = "raft"  # RGB on 0..255, a list of flows: read by the refine job's --net (docs/jobs.md)

    def __init__(self, *, seed: int = 0, iters: int = 6, feature_dim: int = 64, hidden_dim: int = 48,
                 context_dim: int = 32, corr_levels: int = 3, corr_radius: int = 3) -> None:
        super().__init__()
        iters, feature_dim, hidden_dim, context_dim, corr_levels, corr_radius = (
            check_int(value, name, minimum=1) for name, value in (
                ("iters", iters), ("feature_dim", feature_dim), ("hidden_dim", hidden_dim),
                ("context_dim", context_dim), ("corr_levels", corr_levels), ("corr_radius", corr_radius)))
        seed = check_int(seed, "seed")
        if not 0 <= seed < 2**64:  # torch.manual_seed's range; a negative seed would alias a large one
            raise ValueError(f"seed: expected an int with 0 <= seed < 2**64, got {seed!r}")
        self.iters = iters
        self.hidden_dim = hidden_dim
        self.context_dim = context_dim
        self.corr_levels = corr_levels
        self.corr_radius = corr_radius
        device = torch.empty(0).device  # (the default device, a ``with torch.device(...)``'s)
        with torch.device("meta"):  # (shapes only: nothing drawn)
            self.fnet = _Encoder(feature_dim, norm=True)
            self.cnet = _Encoder(hidden_dim + context_dim, norm=False)
            self.update = _UpdateBlock(corr_levels * (2 * corr_radius + 1) ** 2, hidden_dim, context_dim)
        self.to_empty(device="cpu")
        # torch's default initialisation of every convolution, in the order they were built, from a
        # generator of the net's own: the numbers of ``torch.manual_seed(seed)`` and a build, without
        # reading or seeding any global generator (another thread's draws, a build in another thread,
        # the CUDA devices' seeds, which torch.manual_seed sets, are left alone)
        generator = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            for module in self.modules():
                if isinstance(module, nn.Conv2d):
                    nn.init.kaiming_uniform_(module.weight, a=math.sqrt(5), generator=generator)
                    bound = 1 / math.sqrt(module.weight[0].numel())  # (1 / sqrt(fan_in), as nn.Conv2d)
                    nn.init.uniform_(module.bias, -bound, bound, generator=generator)
        if device.type != "cpu":
            self.to(device)

    def extra_repr(self) -> str:
        return f"iters={self.iters}, corr_levels={self.corr_levels}, corr_radius={self.corr_radius}"

    def forward(self, image1: Tensor, image2: Tensor, iters: int | None = None, *,
                final_only: bool = False) -> list[Tensor]:
        """Flow from ``image1`` to ``image2``.

        Args:
            image1, image2: (B, 3, H, W) RGB on 0..255, B >= 1, any H and W >= 1 (images of at
                most 8 x 8 pixels are padded to 8 x 16 inside, as instance norm needs two feature pixels).
                Values outside 0..255 or not finite are a ValueError naming the image, and so is a
                sample whose values all lie in [0, 1], a likely 0..1 image (unless within
                :func:`fsof_torch.trust_image_range`).
            iters: refinement iterations (default: the constructor's).
            final_only: upsample only the last iteration's flow (RAFT's ``test_mode``): the same
                estimate, without the upsampling weights and full-size flows of the iterations
                before it, which only a training loss uses.

        Returns:
            ``iters`` flows (B, 2, H, W) in pixels, coarse to refined; the last is the estimate.
            With ``final_only``, a list of that one flow.
        """
        check_float_tensor(image1, "image1")
        check_float_tensor(image2, "image2")
        dims = check_shape(image1, "image1", ("B", 3, "H", "W"), nonempty=("B", "H", "W"))
        check_shape(image2, "image2", ("B", 3, "H", "W"), dims, nonempty=("B", "H", "W"))
        check_same_device({"image1": image1, "image2": image2})
        iters = self.iters if iters is None else check_int(iters, "iters", minimum=1)
        if not isinstance(final_only, bool):
            raise TypeError(f"final_only: expected a bool, got {type(final_only).__name__}")
        if not skip_values(image1, image2):
            with autocast_off(image1):  # (autocast's stack and cat refuse a half dtype other than its own)
                lo1, hi1, lo2, hi2 = torch.stack([image1.detach().amin(), image1.detach().amax(),
                                                  image2.detach().amin(), image2.detach().amax()]).tolist()
            for name, lo, hi in (("image1", lo1, hi1), ("image2", lo2, hi2)):
                if not (0 <= lo and hi <= 255):  # NaN fails both comparisons
                    raise ValueError(f"{name}: expected values on 0..255 (finite), got the range [{lo:.4g}, {hi:.4g}]")
            # (a sample all within [0, 1], a 0..1 image, ran on as a near-black frame: a flow of nothing, silently)
            for name, image in (("image1", image1), ("image2", image2)):
                check_image_range(image, name, 255.0)
        B, H, W = dims["B"], dims["H"], dims["W"]
        weight = self.fnet.out.weight
        with autocast_off(image1):  # (likewise for a net held in float16 under bfloat16 autocast, or the reverse)
            x = torch.cat([image1.to(weight.dtype), image2.to(weight.dtype)], dim=0) / 127.5 - 1.0
        # Pad symmetrically to a multiple of the stride; replicate so the border carries no edge.
        ph, pw = (-H) % STRIDE, (-W) % STRIDE
        if H + ph == STRIDE and W + pw == STRIDE:
            pw += STRIDE  # instance norm needs 2 feature pixels: H, W <= 8 would give 1, so widen by a stride
        pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        x = F.pad(x, pad, mode="replicate")

        fmap1, fmap2 = self.fnet(x).chunk(2, dim=0)
        # Positions and the flow in at least float32, as RAFT's coordinates, also in a net held in
        # half precision (bfloat16 rounds a position past 128 feature pixels to a whole one, 8 px):
        # the volume sampled in that dtype (as autocast's grid_sample does), the update block fed
        # and the flows returned in x's.
        geo = torch.promote_types(x.dtype, torch.float32)
        pyramid = _correlation_pyramid(fmap1, fmap2, self.corr_levels)
        if x.dtype != geo:
            pyramid = [level.to(geo) for level in pyramid]
        hidden, context = self.cnet(x[:B]).split([self.hidden_dim, self.context_dim], dim=1)
        hidden, context = torch.tanh(hidden), F.relu(context)

        h, w = fmap1.shape[-2:]
        ys, xs = torch.meshgrid(torch.arange(h, dtype=geo, device=x.device),
                                torch.arange(w, dtype=geo, device=x.device), indexing="ij")
        coords0 = torch.stack([xs, ys]).expand(B, 2, h, w)
        flow = torch.zeros_like(coords0)
        flows = []
        for i in range(iters):
            # As RAFT: each iteration learns its own increment; no gradient through the lookup position.
            flow = flow.detach()
            corr = _lookup(pyramid, coords0 + flow, self.corr_radius)
            hidden, delta = self.update(hidden, context, corr.to(x.dtype), flow.to(x.dtype))
            flow = flow + delta
            if final_only and i < iters - 1:
                continue
            up = _convex_upsample(flow, self.update.mask(hidden))
            flows.append(up[:, :, pad[2]:pad[2] + H, pad[0]:pad[0] + W].to(x.dtype))
        return flows
