"""fit_sequence: the mounting calibrated over a clip without poses, the height from poses, the
attitude track; a lazy clip read a pair at a time, with the results of a list of frames;
smooth_attitude against an independent least-squares solution and a dense solve."""

import math
import re
import weakref

import numpy as np
import pytest
import torch

from fsof_torch import Camera
from fsof_torch.data.scene import render_pair, render_sequence
from fsof_torch.estimation.sequence import SequenceFit, fit_sequence, smooth_attitude


def test_smooth_attitude_matches_numpy_least_squares():
    rng = np.random.default_rng(0)
    N = 7
    att, chg = rng.normal(0, 0.01, N), rng.normal(0, 0.002, N)
    sa, sc = rng.uniform(0.005, 0.02, N), rng.uniform(0.0005, 0.002, N)
    rows, rhs = [], []
    for k in range(N):  # (a_k − att_k) / sa_k and (a_{k+1} − a_k − chg_k) / sc_k, written out
        r = np.zeros(N + 1); r[k] = 1 / sa[k]; rows.append(r); rhs.append(att[k] / sa[k])
        r = np.zeros(N + 1); r[k + 1], r[k] = 1 / sc[k], -1 / sc[k]; rows.append(r); rhs.append(chg[k] / sc[k])
    A, b = np.array(rows), np.array(rhs)
    expected = np.linalg.lstsq(A, b, rcond=None)[0]
    std = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    track, sigma = smooth_attitude(torch.tensor(att), torch.tensor(chg), torch.tensor(sa), torch.tensor(sc))
    np.testing.assert_allclose(track.numpy(), expected, atol=1e-10)
    np.testing.assert_allclose(sigma.numpy(), std, rtol=1e-6)


def test_smooth_attitude_names_a_measurement_on_the_meta_device():
    """The track is solved on the host: an attitude or change on the meta device (no values to
    bring there) raised torch's NotImplementedError "Cannot copy out of meta tensor; no data!",
    naming neither. Now a ValueError names it, as its sigmas were named."""
    att, chg = torch.tensor([0.01, 0.02, 0.0]), torch.tensor([0.001, -0.002, 0.0])
    for name, args in (("attitude", (att.to("meta"), chg)), ("change", (att, chg.to("meta")))):
        with pytest.raises(ValueError, match=rf"^{name}: a tensor on the meta device has shapes but no values"):
            smooth_attitude(*args, 0.01, 0.001)
    track, sigma = smooth_attitude(att, chg, 0.01, 0.001)
    assert track.device.type == "cpu" and track.shape == (4,) and bool(torch.isfinite(sigma).all())


def _dense_smooth(att, chg, sa, sc):
    """The normal equations of smooth_attitude's least squares, dense (N + 1) × (N + 1), solved
    and inverted by torch.linalg (with the same 1e-12 ridge)."""
    N = att.shape[0]
    wa, wc = 1 / sa.square(), 1 / sc.square()
    A = torch.zeros(N + 1, N + 1, dtype=torch.float64)
    b = torch.zeros(N + 1, dtype=torch.float64)
    for k in range(N):
        A[k, k] += wa[k]
        b[k] += wa[k] * att[k]
        A[k:k + 2, k:k + 2] += wc[k] * torch.tensor([[1.0, -1.0], [-1.0, 1.0]], dtype=torch.float64)
        b[k] -= wc[k] * chg[k]
        b[k + 1] += wc[k] * chg[k]
    A += 1e-12 * torch.eye(N + 1, dtype=torch.float64)
    return torch.linalg.solve(A, b), torch.linalg.inv(A).diagonal().sqrt()


@pytest.mark.parametrize("seed", range(12))
def test_smooth_attitude_matches_a_dense_solve(seed):
    """Random clips of 1 to 40 pairs, some measurements with infinite σ (they do not count); every
    stretch joined by finite changes keeps one finite attitude, as _track guarantees (a frame no
    measurement reaches rests on the ridge alone: the last one when its change is infinite)."""
    g = torch.Generator().manual_seed(seed)
    N = 1 if seed == 0 else int(torch.randint(1, 41, (1,), generator=g))
    f64 = dict(dtype=torch.float64)
    att, chg = 0.01 * torch.randn(N, generator=g, **f64), 0.002 * torch.randn(N, generator=g, **f64)
    sa = 0.005 + 0.015 * torch.rand(N, generator=g, **f64)
    sc = 0.0005 + 0.0015 * torch.rand(N, generator=g, **f64)
    if N > 1:
        sa[1:] = torch.where(torch.rand(N - 1, generator=g) < 0.3, math.inf, sa[1:])
        sc = torch.where(torch.rand(N, generator=g) < 0.2, math.inf, sc)
        sa[1:] = torch.where(sc[:-1].isinf(), 0.01, sa[1:])  # a stretch after a broken link starts measured
    track, sigma = smooth_attitude(att, chg, sa, sc)
    expected, std = _dense_smooth(att, chg, sa, sc)
    assert track.shape == sigma.shape == (N + 1,) and track.dtype == sigma.dtype == torch.float64
    torch.testing.assert_close(track, expected, rtol=1e-10, atol=1e-10 * float(expected.abs().max()))
    torch.testing.assert_close(sigma, std, rtol=1e-10, atol=0)


def _exact_smooth(att, chg, sa, sc):
    """smooth_attitude's least squares (with its 1e-12 ridge) solved in exact rational arithmetic
    (Gauss–Jordan on the normal equations with the identity beside them): the track and the square
    roots of the inverse's diagonal, rounded to float once at the end."""
    from fractions import Fraction

    N = len(att)
    n = N + 1
    wa, wc = [1 / Fraction(s) ** 2 for s in sa], [1 / Fraction(s) ** 2 for s in sc]
    A = [[Fraction(0)] * n for _ in range(n)]
    b = [Fraction(0)] * n
    for k in range(N):
        A[k][k] += wa[k]
        b[k] += wa[k] * Fraction(att[k])
        for i, j, sign in ((k, k, 1), (k + 1, k + 1, 1), (k, k + 1, -1), (k + 1, k, -1)):
            A[i][j] += sign * wc[k]
        b[k] -= wc[k] * Fraction(chg[k])
        b[k + 1] += wc[k] * Fraction(chg[k])
    M = [A[i] + [b[i]] + [Fraction(int(i == j)) for j in range(n)] for i in range(n)]
    for i in range(n):
        M[i][i] += Fraction(1e-12)
    for i in range(n):
        M[i] = [v / M[i][i] for v in M[i]]
        for j in range(n):
            if j != i and M[j][i]:
                M[j] = [v - M[j][i] * w for v, w in zip(M[j], M[i])]
    return (torch.tensor([float(M[i][n]) for i in range(n)], dtype=torch.float64),
            torch.tensor([float(M[i][n + 1 + i]) for i in range(n)], dtype=torch.float64).sqrt())


@pytest.mark.parametrize("change_sigma", [1e-3, 1e-6, 1e-8, 1e-10, 1e-13])
def test_smooth_attitude_is_exact_however_much_the_changes_outweigh_the_attitudes(change_sigma):
    """Attitudes within 1° and changes known to ``change_sigma`` rad: the textbook LDLᵀ recurrence
    cancelled, its pivot the difference of two numbers of the changes' weight. At 1e-8 rad the track
    was 1e-6 rad off the exact solution (its σ 3e-4 relatively), at 1e-10 rad the last pivot came out
    0, a ZeroDivisionError. Against the exact rational solve, to float64's rounding."""
    rng = np.random.default_rng(3)
    N = 8
    att, chg = rng.normal(0, 0.01, N), rng.normal(0, 0.001, N)
    sa, sc = [math.radians(1.0)] * N, [change_sigma] * N
    want, want_sigma = _exact_smooth(att, chg, sa, sc)
    f64 = dict(dtype=torch.float64)
    track, sigma = smooth_attitude(torch.tensor(att, **f64), torch.tensor(chg, **f64), torch.tensor(sa, **f64),
                                   torch.tensor(sc, **f64))
    torch.testing.assert_close(track, want, rtol=0, atol=1e-15)
    torch.testing.assert_close(sigma, want_sigma, rtol=1e-13, atol=0)


def test_smooth_attitude_ignores_infinite_sigma():
    att = torch.tensor([0.0, 5.0, 0.0], dtype=torch.float64)  # the middle one is an outlier
    chg = torch.zeros(3, dtype=torch.float64)
    track, _ = smooth_attitude(att, chg, torch.tensor([1.0, math.inf, 1.0]), 1.0)
    assert torch.allclose(track, torch.zeros(4, dtype=torch.float64), atol=1e-9)
    # a measurement that does not count may be anything, NaN too
    att[1] = math.nan
    again, _ = smooth_attitude(att, chg, torch.tensor([1.0, math.inf, 1.0]), 1.0)
    assert torch.equal(again, track)
    # none counts: the changes fix the track only up to a constant (was: ZeroDivisionError, or
    # standard deviations of 1e5 rad from the ridge)
    with pytest.raises(ValueError, match=r"^attitude_sigma: expected at least one value whose 1 / σ² is > 0 .*, got "
                                         r"smallest inf"):
        smooth_attitude(att, chg, math.inf, math.radians(0.03))


def test_smooth_attitude_frames_no_counting_measurement_reaches_are_not_placed():
    """As its docstring says: the last frame, its change not counting, comes back 0 ± 1e6 rad; four
    frames tied to each other by their changes but to no counting attitude come back with their
    changes' differences, their mean 0, each ± 1e6 / √4 rad; the frames that count are as alone."""
    f64 = dict(dtype=torch.float64)
    track, sd = smooth_attitude(torch.tensor([0.5, 0.2], **f64), torch.tensor([0.1, 0.1], **f64), 1.0,
                                torch.tensor([0.1, math.inf], **f64))
    alone, alone_sd = smooth_attitude(torch.tensor([0.5, 0.2], **f64), torch.tensor([0.1, 0.1], **f64), 1.0, 0.1)
    assert track[2].item() == 0.0 and sd[2].item() == pytest.approx(1e6, rel=1e-9)
    assert torch.allclose(track[:2], alone[:2], atol=1e-9) and torch.allclose(sd[:2], alone_sd[:2], atol=1e-9)
    att, chg = torch.tensor([0.5, 0.2, 0.3, 0.4], **f64), torch.tensor([0.1, 0.1, 0.2, 0.3], **f64)
    track, sd = smooth_attitude(att, chg, torch.tensor([1.0, math.inf, math.inf, math.inf], **f64),
                                torch.tensor([math.inf, 0.1, 0.1, 0.1], **f64))
    assert track[0].item() == pytest.approx(0.5, abs=1e-9) and sd[0].item() == pytest.approx(1.0, rel=1e-9)
    assert torch.allclose(track[2:] - track[1:-1], chg[1:], atol=1e-9)
    assert abs(track[1:].mean().item()) < 1e-9
    assert torch.allclose(sd[1:], torch.full((4,), 5e5, **f64), rtol=1e-6)


@pytest.mark.parametrize("args, error, match", [
    ((torch.zeros(3), torch.zeros(4), 1.0, 1.0), ValueError, r"^change: expected 3 values \(attitude's\), got 4"),
    ((torch.zeros(2, 3), torch.zeros(2, 3), 1.0, 1.0), ValueError, r"^attitude: expected a 1-D tensor"),
    (([0.0, 0.0], torch.zeros(2), 1.0, 1.0), TypeError, r"^attitude: expected a torch.Tensor, got list"),
    ((torch.zeros(3), torch.zeros(3), 0.0, 1.0), ValueError, r"^attitude_sigma: expected values > 0"),
    ((torch.zeros(3), torch.zeros(3), 1.0, math.nan), ValueError, r"^change_sigma: expected values > 0"),
    ((torch.zeros(3), torch.zeros(3), torch.ones(2), 1.0), ValueError, r"^attitude_sigma: expected a number or a ten"),
    ((torch.zeros(3), torch.zeros(3), True, 1.0), TypeError, r"^attitude_sigma: expected a number"),
    ((torch.tensor([0.0, math.nan, 0.0]), torch.zeros(3), 1.0, 1.0), ValueError, r"^attitude: expected finite values"),
    # no pair: a track of one frame that nothing measures (it came back 0 ± 1e6 rad)
    ((torch.zeros(0), torch.zeros(0), 1.0, 1.0), ValueError, r"^attitude: expected at least one value \(one per pair\)"),
])
def test_smooth_attitude_refuses_bad_input(args, error, match):
    with pytest.raises(error, match=match):
        smooth_attitude(*args)


def test_smooth_attitude_names_where_a_long_tracks_bad_value_is():
    """A NaN attitude of a 10 000-pair track was quoted with all 10 000 values (a 50 kB message),
    and a σ of 0 at [3] as a tensor repr that elides the middle ("tensor([1., 1., 1., ..., 1.])"),
    naming neither the value nor its place. The message now gives the first three with their
    indices."""
    n = 10_000
    attitude = torch.zeros(n, dtype=torch.float64)
    attitude[5000] = math.nan
    with pytest.raises(ValueError, match=r"^attitude: expected finite values where the sigma is finite, got nan at "
                                         r"\[5000\]$"):
        smooth_attitude(attitude, torch.zeros(n), 1.0, 1.0)
    sigma = torch.ones(n).index_fill(0, torch.tensor([3, 7, 9, 11]), 0.0)
    with pytest.raises(ValueError, match=r"^attitude_sigma: expected values > 0 \(inf: the measurement does not count\), "
                                         r"got 0.0 at \[3\], 0.0 at \[7\], 0.0 at \[9\] and 1 more$"):
        smooth_attitude(torch.zeros(n), torch.zeros(n), sigma, 1.0)
    with pytest.raises(ValueError, match=r"^change_sigma: expected values > 0 .*, got nan$"):
        smooth_attitude(torch.zeros(3), torch.zeros(3), 1.0, torch.tensor(math.nan))
    with pytest.raises(ValueError, match=r"^change: expected finite values where the sigma is finite, got inf at "
                                         r"\[1\]$"):  # (an inf at [2], whose σ is inf, does not count)
        smooth_attitude(torch.zeros(3), torch.tensor([0.0, math.inf, math.inf]), 1.0,
                        torch.tensor([1.0, 1.0, math.inf]))


def test_smooth_attitude_takes_numpy_numbers_and_refuses_sigmas_too_small_to_weigh():
    att, chg = torch.tensor([0.01, 0.02]), torch.tensor([0.01, 0.0])
    track, sigma = smooth_attitude(att, chg, np.float64(0.01), np.float32(0.001))
    ref_track, ref_sigma = smooth_attitude(att, chg, 0.01, float(np.float32(0.001)))
    assert torch.equal(track, ref_track) and torch.equal(sigma, ref_sigma)
    # (1 / σ² overflowed to inf and the track came back NaN, without an error)
    with pytest.raises(ValueError, match=r"^attitude_sigma: expected values whose 1 / σ² is finite .*got 1e-200"):
        smooth_attitude(att, chg, 1e-200, 1.0)


def test_robust_mean_of_an_even_count_is_not_the_lower_value():
    """torch's ``median`` takes the lower middle value: with two successful pairs the deviation
    was 0 and the mounting came out as the smaller of their two attitudes, not their mean."""
    from fsof_torch.estimation.sequence import _robust_mean

    ok = torch.ones(2, dtype=torch.bool)
    assert _robust_mean(torch.tensor([0.01, -0.01], dtype=torch.float64), ok) == pytest.approx(0.0, abs=1e-15)
    # an outlier is still left out; a failed pair counts for nothing
    x = torch.tensor([0.010, 0.011, 0.012, 0.013, 0.5, -7.0], dtype=torch.float64)
    ok = torch.tensor([True, True, True, True, True, False])
    assert _robust_mean(x, ok) == pytest.approx(0.0115, abs=1e-12)


def test_robust_mean_cuts_at_three_normal_consistent_deviations():
    """The cut is 3 σ̂ with σ̂ = 1.4826 MAD (the normal distribution's σ), written here with NumPy:
    a value 4 MADs out (2.7 σ̂) is kept, one 4.7 MADs out (3.2 σ̂) is left out."""
    from fsof_torch.estimation.sequence import _robust_mean

    for far, kept in ((8.5, True), (9.5, False)):
        x = np.array([0.0, 1.0, 2.0, 3.0, 4.0, far])
        med = np.median(x)
        sigma = 1.4826 * np.median(np.abs(x - med))
        ref = x[np.abs(x - med) <= 3 * sigma].mean()
        assert (len(x[np.abs(x - med) <= 3 * sigma]) == 6) == kept
        got = _robust_mean(torch.from_numpy(x), torch.ones(6, dtype=torch.bool))
        assert got == pytest.approx(ref, abs=1e-12), far


def test_robust_mean_weighs_the_kept_values_by_their_inverse_variance():
    """With variances, the kept values' mean is Σ x / v / Σ 1 / v (written out here); the cut is
    the same as without them. A variance of 0 (a held angle) or inf weighs them alike."""
    from fsof_torch.estimation.sequence import _robust_mean

    x = torch.tensor([0.10, 0.11, 0.12, 0.13, 0.14, 5.0], dtype=torch.float64)
    var = torch.tensor([1.0, 4.0, 0.25, 1.0, 2.0, 1e-6], dtype=torch.float64)
    ok = torch.ones(6, dtype=torch.bool)
    kept, w = x[:5].numpy(), 1 / var[:5].numpy()
    assert _robust_mean(x, ok, var) == pytest.approx(float((w * kept).sum() / w.sum()), abs=1e-15)
    for bad in (0.0, math.inf):
        held = var.clone()
        held[2] = bad
        assert _robust_mean(x, ok, held) == pytest.approx(float(kept.mean()), abs=1e-15)
    ok[0] = False  # (a failed value leaves its variance out too)
    kept, w = x[1:5].numpy(), 1 / var[1:5].numpy()
    assert _robust_mean(x, ok, var) == pytest.approx(float((w * kept).sum() / w.sum()), abs=1e-15)


def test_robust_mean_of_fewer_than_five_is_their_median():
    """Of 3 or 4 values the median absolute deviation is set by the nearer outer value: pitches of
    1.00, 1.05 and 1.30 degrees (a spread the body's pitching gives) calibrated at the mean of the
    first two, 1.30 dropped by a deviation 1.05 alone set. Below five the median stands in, which a
    far value does not move either; from five on an outlier is still left out."""
    from fsof_torch.estimation.sequence import _robust_mean

    ones = lambda n: torch.ones(n, dtype=torch.bool)  # noqa: E731
    deg = torch.tensor([1.00, 1.05, 1.30], dtype=torch.float64) * math.pi / 180
    assert _robust_mean(deg, ones(3)) == pytest.approx(1.05 * math.pi / 180, abs=1e-15)
    far = torch.tensor([1.00, 1.05, 7.0], dtype=torch.float64)  # (a fit that succeeded far off)
    assert _robust_mean(far, ones(3)) == pytest.approx(1.05, abs=1e-15)
    four = torch.tensor([1.00, 1.04, 1.06, 9.0], dtype=torch.float64)
    assert _robust_mean(four, ones(4)) == pytest.approx(1.05, abs=1e-12)
    # (failed pairs count for nothing: three successful ones of five)
    x = torch.tensor([1.00, 9.0, 1.05, 1.30, -9.0], dtype=torch.float64)
    assert _robust_mean(x, torch.tensor([True, False, True, True, False])) == pytest.approx(1.05, abs=1e-12)
    five = torch.tensor([1.00, 1.02, 1.04, 1.06, 3.0], dtype=torch.float64)
    assert _robust_mean(five, ones(5)) == pytest.approx(1.03, abs=1e-12)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def body_motion_clip(one_thread):
    pairs = render_sequence("body-motion", 4, seed=0)
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    poses = torch.stack([p["pose1"] for p in pairs] + [pairs[-1]["pose2"]])
    return pairs, frames, poses


@pytest.fixture(scope="module")
def body_motion_fit(body_motion_clip):
    pairs, frames, poses = body_motion_clip
    return fit_sequence(frames, [p["road"] for p in pairs], pairs[0]["camera"], poses=poses)


def test_fit_sequence_calibrates_the_mounting_and_height(body_motion_clip, body_motion_fit):
    pairs, frames, _ = body_motion_clip
    seq = body_motion_fit
    assert isinstance(seq, SequenceFit) and len(seq.fits) == len(pairs)
    nominal = pairs[0]["camera"]
    true_pitch = float(np.mean([p["plane"]["pitch"] for p in pairs]))
    true_roll = float(np.mean([p["plane"]["roll"] for p in pairs]))
    # the nominal mounting is about a degree off the body-motion preset's attitude over the road
    assert abs(float(nominal.pitch) - true_pitch) > 0.5 * math.pi / 180
    assert abs(seq.mounting["pitch"] - true_pitch) < 0.3 * math.pi / 180
    assert abs(seq.mounting["roll"] - true_roll) < 0.3 * math.pi / 180
    # metric scale from the poses: the camera height over the road within 2 %
    assert seq.mounting["height"] == pytest.approx(pairs[0]["plane"]["height"], rel=0.02)
    assert float(seq.camera.pitch) == pytest.approx(seq.mounting["pitch"])
    for k, p in enumerate(pairs):
        road = (p["road"] & p["valid"])[0]
        epe = float((seq.fits[k].flow[0] - p["flow"]).norm(dim=0)[road].mean())
        assert epe < 1.0, (k, epe)
        assert seq.params["z_d"][k] == pytest.approx(float(seq.fits[k].params["z_d"][0]))
    assert set(seq.first_pass) == set(seq.params)
    assert 0 < seq.calibrated_from <= len(pairs)


class LazySequence:
    """Tensors made on demand (a fresh copy on ``seq[k]``): it counts the reads, and, through weak
    references, the tensors it made that are still alive when it makes another."""

    def __init__(self, items):
        self.items, self.reads, self.alive, self.most_alive = items, [0] * len(items), [], 0

    def __len__(self):
        return len(self.items)

    def __getitem__(self, k):
        self.reads[k] += 1
        item = self.items[k].clone()
        self.alive = [r for r in self.alive if r() is not None] + [weakref.ref(item)]
        self.most_alive = max(self.most_alive, len(self.alive))
        return item


def test_fit_sequence_reads_a_lazy_clip_a_pair_at_a_time(body_motion_clip, body_motion_fit):
    """Frames and masks made on demand: each read once per pass, in order, at most the two frames
    of a pair alive at once; with keep_fits=False no fit is kept, and the results are those of the
    list of frames."""
    pairs, frames, poses = body_motion_clip
    clip, masks = LazySequence(frames), LazySequence([p["road"] for p in pairs])
    seq = fit_sequence(clip, masks, pairs[0]["camera"], poses=poses, keep_fits=False)
    assert clip.reads == [2] * len(frames) and masks.reads == [2] * len(pairs)
    assert clip.most_alive <= 2 and masks.most_alive <= 1
    assert seq.fits == []
    ref = body_motion_fit
    for got, want in ((seq.params, ref.params), (seq.first_pass, ref.first_pass)):
        assert set(got) == set(want) and all(torch.equal(got[k], want[k]) for k in want)
    assert seq.mounting == ref.mounting
    assert torch.equal(seq.success, torch.stack([f.success.all() for f in ref.fits]))
    assert seq.success.dtype == torch.bool and seq.success.shape == (len(pairs),)



def test_fit_sequence_second_pass_starts_at_the_smoothed_track(body_motion_clip, monkeypatch):
    """The second pass fits every pair again, started at the smoothed attitude track (computed here
    with smooth_attitude from the first pass: attitude σ = attitude_deg for each successful pair,
    change σ = 0.1 · body_rotation_deg) and tied to it by a prior of the track's σ; its fits are
    the returned parameters, which differ from the first pass's."""
    import fsof_torch.estimation.sequence as sequence

    pairs, frames, _ = body_motion_clip
    calls = []

    def spy(*args, **kwargs):
        fit = fit_image(*args, **kwargs)
        calls.append((kwargs["init"], kwargs["prior"], {n: v.clone() for n, v in fit.params.items()}))
        return fit

    fit_image = sequence.fit_image
    monkeypatch.setattr(sequence, "fit_image", spy)
    n_pairs = 3
    seq = fit_sequence(frames[:n_pairs + 1], pairs[0]["road"], pairs[0]["camera"], keep_fits=False, max_points=2000)
    assert len(calls) == 2 * n_pairs and bool(seq.success.all())
    assert all(init is None for init, _, _ in calls[:n_pairs])
    deg = math.pi / 180
    for name in ("roll", "pitch"):
        track, sigma = smooth_attitude(seq.first_pass[name], seq.first_pass[name + "_change"], 1.0 * deg,
                                       0.1 * 0.3 * deg)
        for k, (init, prior, params) in enumerate(calls[n_pairs:]):
            assert float(init[name]) == pytest.approx(float(track[k]), abs=1e-12)
            assert float(init[name + "_change"]) == pytest.approx(float(track[k + 1] - track[k]), abs=1e-12)
            mean, std = prior[name]
            assert float(mean) == pytest.approx(float(track[k]), abs=1e-12)
            assert float(std) == pytest.approx(float(sigma[k]), rel=1e-6)
            mean, std = prior[name + "_change"]  # (the change: not the track's σ, the smoothing's)
            assert float(mean) == pytest.approx(float(track[k + 1] - track[k]), abs=1e-12)
            assert float(std) == pytest.approx(0.1 * 0.3 * deg, rel=1e-12)
            assert float(seq.params[name][k]) == pytest.approx(float(params[name][0]), abs=1e-12)
        assert not torch.equal(seq.params[name], seq.first_pass[name])

def test_fit_sequence_without_poses_has_no_height(body_motion_clip):
    pairs, frames, _ = body_motion_clip
    seq = fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], passes=1, max_points=1000)
    assert "height" not in seq.mounting and len(seq.fits) == 2
    assert seq.fits is not None and seq.params["x_d"].shape == (2,)


def test_fit_sequence_leaves_inputs_alone(body_motion_clip):
    pairs, frames, _ = body_motion_clip
    before = [f.clone() for f in frames[:3]]
    fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], passes=1, max_points=500)
    assert all(torch.equal(a, b) for a, b in zip(before, frames[:3]))


def test_fit_sequence_checks_fit_image_options_before_reading_a_frame(body_motion_clip):
    """A bad value among the options it forwards to fit_image is an error at once, not after the
    clip's first pairs were fitted: no frame is read."""
    pairs, frames, _ = body_motion_clip
    clip = LazySequence(frames)
    for options, error, match in (({"smooth_sigma": -1.0}, ValueError, "^smooth_sigma: expected a number >= 0"),
                                  ({"fine_points": 2.5}, TypeError, "^fine_points: expected None or an int"),
                                  ({"prior": None}, TypeError, r"^options: options \['prior'\] of fit_image are set"),
                                  # (bounds of another batch than a pair's 1: after the first pair's two
                                  # frames were read, at its fit)
                                  ({"bounds": (torch.zeros(3, 8), torch.ones(3, 8))}, ValueError,
                                   r"^bounds \(lower\): expected shape \(1, 8\)")):
        with pytest.raises(error, match=match):
            fit_sequence(clip, pairs[0]["road"], pairs[0]["camera"], **options)
    assert clip.reads == [0] * len(frames)

def test_fit_sequence_errors(body_motion_clip):
    pairs, frames, _ = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    with pytest.raises(ValueError, match="frames: expected at least 2"):
        fit_sequence(frames[:1], road, cam)
    with pytest.raises(ValueError, match="passes: expected 1 or 2, got 3"):
        fit_sequence(frames[:3], road, cam, passes=3)
    for name in ("attitude_deg", "body_rotation_deg"):
        with pytest.raises(ValueError, match=f"{name}: expected a finite number of degrees > 0"):
            fit_sequence(frames[:3], road, cam, **{name: 0.0})
    with pytest.raises(ValueError, match="mask: expected one mask or 2"):
        fit_sequence(frames[:3], [road] * 3, cam)
    with pytest.raises(ValueError, match="flows: expected 2"):
        fit_sequence(frames[:3], road, cam, flows=[torch.zeros(2, 8, 8)])
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera of batch 1"):
        fit_sequence(frames[:3], road, "cam")
    with pytest.raises(ValueError, match="model: a clip is fitted with the 'plane' model"):
        fit_sequence(frames[:3], road, cam, model="paper")
    two = Camera(cam.K.expand(2, -1, -1), height=1.65)
    with pytest.raises(ValueError, match=r"^camera: expected batch 1 \(one camera for the clip\), got 2$"):
        fit_sequence(frames[:3], road, two)
    with pytest.raises(TypeError, match="^camera: expected a fsof_torch.Camera of batch 1, got str$"):
        fit_sequence(frames[:3], road, "cam")
    # flags and the pass count are checked, not taken for their truth value (True == 1)
    for bad in (True, 1.0, 2.0):  # (a wrong type: TypeError; 3, a wrong value, above: ValueError)
        with pytest.raises(TypeError, match=f"^passes: expected 1 or 2, got {bad!r}$"):
            fit_sequence(frames[:3], road, cam, passes=bad)
    for name in ("keep_fits", "progress"):
        with pytest.raises(TypeError, match=f"^{name}: expected True or False, got str 'no'$"):
            fit_sequence(frames[:3], road, cam, **{name: "no"})
    with pytest.raises(ValueError, match=r"poses: expected a float tensor of shape \(3, 4, 4\) \(one per frame\), "
                                         r"got torch.float32 \(2, 4, 4\)"):
        fit_sequence(frames[:3], road, cam, poses=torch.eye(4).expand(2, 4, 4))
    # integer poses (a wrong dtype) raised a ValueError
    with pytest.raises(TypeError, match=r"^poses: expected a float tensor of shape \(3, 4, 4\) \(one per frame\), "
                                        r"got dtype torch.int64$"):
        fit_sequence(frames[:3], road, cam, poses=torch.eye(4, dtype=torch.int64).expand(3, 4, 4))
    # poses in millimetres (1.2 m a frame read as 1200 m), named before any fit
    mm = torch.eye(4).repeat(3, 1, 1)
    mm[:, 2, 3] = torch.tensor([0.0, 1200.0, 2400.0])
    with pytest.raises(ValueError, match=r"^poses: the pose of frames\[0\] and the pose of frames\[1\] lie 1200 m "
                                         r"apart, farther than a road vehicle travels .*millimetres"):
        fit_sequence(frames[:3], road, cam, poses=mm)
    # (torch's own message, naming nothing, for poses it could not convert)
    with pytest.raises(TypeError, match=r"^poses: expected a float tensor of shape \(3, 4, 4\) \(one per frame\), "
                                         r"got list"):
        fit_sequence(frames[:3], road, cam, poses=[[["a"] * 4] * 4] * 3)
    # a list of poses of other shapes (a KITTI row 3 x 4 among them) raised torch.stack's RuntimeError
    with pytest.raises(TypeError, match=r"^poses: expected a float tensor of shape \(3, 4, 4\) \(one per frame\), "
                                        r"got list \(stack expects each tensor to be equal size"):
        fit_sequence(frames[:3], road, cam, poses=[torch.eye(4), torch.eye(4)[:3], torch.eye(4)])
    # each item is checked as it is read (named by its index), before any fit
    H, W = frames[0].shape[-2:]
    with pytest.raises(TypeError, match="frames: expected a sequence of tensors"):
        fit_sequence(None, road, cam)
    with pytest.raises(TypeError, match="mask: expected a sequence of tensors"):
        fit_sequence(frames[:3], None, cam)
    # a NumPy mask was read as a sequence of masks (its rows): "expected one mask or 2, got 1"
    with pytest.raises(TypeError, match=r"^mask: expected a bool tensor \(1, H, W\) or a sequence of them, got "
                                        rf"ndarray of shape \(1, {H}, {W}\)$"):
        fit_sequence(frames[:3], road.numpy(), cam)
    with pytest.raises(ValueError, match=r"frames\[0\]: expected shape \(C, H, W\) or \(1, C, H, W\) with C 1 or 3 "
                                          r"\(an image\), got \(2, 3, "):
        fit_sequence([torch.stack([f, f]) for f in frames[:3]], road, cam)
    # an RGBA frame (or one (H, W, 3)) has the shape (C, H, W): the message said no more
    rgba, hwc = [torch.cat([f, torch.full_like(f[:1], 255)]) for f in frames[:3]], [f.permute(1, 2, 0) for f in frames[:3]]
    for bad in (rgba, hwc):
        with pytest.raises(ValueError, match=r"^frames\[0\]: expected shape \(C, H, W\) or \(1, C, H, W\) with C 1 "
                                             rf"or 3 \(an image\), got {re.escape(str(tuple(bad[0].shape)))}$"):
            fit_sequence(bad, road, cam)
    with pytest.raises(ValueError, match=rf"frames\[1\]: expected shape \(3, {H}, {W}\)"):
        fit_sequence([frames[0], frames[1][..., :-8], frames[2]], road, cam)
    # frames of one row or column: named by their index (fit_image named its image1)
    for cut in ((slice(None), slice(0, 1)), (slice(None), slice(None), slice(0, 1))):
        with pytest.raises(ValueError, match=r"^frames\[0\]: expected an image of at least 2x2 pixels \(the image "
                                             rf"fit's\), got shape {re.escape(str(tuple(frames[0][cut].shape)))}$"):
            fit_sequence([f[cut] for f in frames[:3]], road[cut], cam)
    with pytest.raises(ValueError, match=rf"mask: expected shape \(1, {H}, {W}\) or \(1, 1, {H}, {W}\)"):
        fit_sequence(frames[:3], road[None].expand(2, -1, -1, -1), cam)
    with pytest.raises(TypeError, match=r"mask\[0\]: expected a bool tensor, got dtype torch.float32"):
        fit_sequence(frames[:3], [road.float(), road.float()], cam)
    with pytest.raises(ValueError, match=rf"flows\[0\]: expected shape \(2, {H}, {W}\)"):
        fit_sequence(frames[:3], road, cam, flows=[torch.zeros(2, H - 8, W), torch.zeros(2, H, W)])
    for dtype in (torch.int64, torch.bool):  # (taken as pixels once, truncated)
        with pytest.raises(TypeError, match=rf"^flows\[1\]: expected a floating-point tensor, got dtype {dtype}$"):
            fit_sequence(frames[:3], road, cam, flows=[torch.zeros(2, H, W), torch.zeros(2, H, W, dtype=dtype)],
                         passes=1, max_points=500)
    for name in ("image1", "image2"):  # fit_image's arguments the clip sets itself
        with pytest.raises(TypeError, match=rf"options: options \['{name}'\] of \w+ are set by the function that forwards"):
            fit_sequence(frames[:3], road, cam, **{name: frames[0]})
    # a bad frame is named by its index (not as the pair's image1 / image2 of the fit it feeds)
    bad = frames[1].clone()
    bad[0, 0, 0] = math.nan
    for frame, error, match in ((frames[1].to(torch.uint8), TypeError, r"^frames\[1\]: expected a floating-point"),
                                (frames[1][:1], ValueError, r"^frames\[1\]: expected shape \(3, "),
                                (bad, ValueError, r"^frames\[1\]: expected finite pixel values"),
                                (frames[1] / 255, ValueError, r"^frames\[1\]: values in .* look like 0..1 images")):
        with pytest.raises(error, match=match):
            fit_sequence([frames[0], frame, frames[2]], road, cam)


def test_fit_sequence_takes_frames_on_the_given_data_range(body_motion_clip):
    """Frames on 0..1 with data_range=1.0 (fit_image's option) fit as the same frames on 0..255."""
    pairs, frames, _ = body_motion_clip
    options = dict(passes=1, max_points=500)
    on_255 = fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], **options)
    on_1 = fit_sequence([f / 255 for f in frames[:3]], pairs[0]["road"], pairs[0]["camera"], data_range=1.0,
                        **options)
    for name, value in on_255.params.items():
        torch.testing.assert_close(on_1.params[name], value, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match=r"^frames\[0\]: "):  # (0..255 frames checked against the range given)
        fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], data_range=1.0, **options)


def test_fit_sequence_one_pass_with_poses_gives_metres_at_the_calibrated_height(body_motion_clip):
    """With poses and passes=1 the translations (params and fits) are in metres at the returned
    camera's height, the fits' cameras at that height: the pass without poses, scaled."""
    pairs, frames, poses = body_motion_clip
    nominal = pairs[0]["camera"]
    options = dict(passes=1, max_points=1000)
    plain = fit_sequence(frames[:3], pairs[0]["road"], nominal, **options)
    # poses of a world 1.5 times larger: the camera 1.5 times higher than the nominal height
    larger = poses[:3].clone()
    larger[:, :3, 3] *= 1.5
    metric = fit_sequence(frames[:3], pairs[0]["road"], nominal, poses=larger, **options)
    ratio = metric.mounting["height"] / float(nominal.height[0])
    assert ratio == pytest.approx(1.5, rel=0.02)
    # two pairs that succeed calibrate the mounting at the mean of their attitudes (once the lower one)
    assert bool(plain.success.all())
    for name in ("roll", "pitch"):
        assert plain.mounting[name] == pytest.approx(float(plain.first_pass[name].double().mean()), abs=1e-9)
    assert float(metric.camera.height[0]) == pytest.approx(metric.mounting["height"])
    for name, value in plain.params.items():
        scale = ratio if name in ("x_d", "y_d", "z_d") else 1.0
        torch.testing.assert_close(metric.params[name], value * scale, rtol=1e-6, atol=1e-9)  # (float32 fits)
        torch.testing.assert_close(metric.first_pass[name], value, rtol=0, atol=0)
    for k, (fit, before) in enumerate(zip(metric.fits, plain.fits)):
        assert torch.equal(fit.camera.height, metric.camera.height.to(fit.camera.height))
        assert float(fit.params["z_d"][0]) == pytest.approx(float(metric.params["z_d"][k]))
        assert float(fit.params["z_d"][0]) == pytest.approx(1.5 * pairs[k]["plane"]["z_d"], rel=0.03)
        assert torch.equal(fit.flow, before.flow) and torch.equal(fit.homography, before.homography)
        i = list(fit.params).index("z_d")
        assert float(fit.covariance[0, i, i]) == pytest.approx(float(before.covariance[0, i, i]) * ratio ** 2)


def test_fit_sequence_bars_in_a_log_are_rate_limited(body_motion_clip, monkeypatch):
    """Its passes' bars (tqdm on stderr) were redrawn as tqdm redraws on a terminal in a log too
    (CI, a file): they are the library's rate-limited bars."""
    import io
    import sys

    import fsof_torch.io.progress as progress

    pairs, frames, _ = body_motion_clip
    bars, original = [], progress.progress_bar

    def recorded(*args, **options):
        bars.append(original(*args, **options))
        return bars[-1]

    monkeypatch.setattr(progress, "progress_bar", recorded)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # (not a terminal)
    fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], passes=2, max_points=500, progress=True)
    log = sys.stderr.getvalue()
    assert len(bars) == 2 and all(bar.mininterval == progress.LOG_INTERVAL for bar in bars)
    assert "road motion: first pass" in log and "2/2" in log


def test_fit_sequence_poses_still_in_half_the_moving_pairs_give_no_scale(body_motion_clip):
    """Poses that stand still in one of two pairs whose images move contradict them: the median
    ratio would be half the other pair's (once the lower median gave 0), so no scale is taken."""
    pairs, frames, poses = body_motion_clip
    half = poses[[0, 0, 2]]
    with pytest.raises(ValueError, match=r"^poses: their translations give no scale"):
        fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], poses=half, passes=1, max_points=500)


def test_fit_sequence_poses_that_wait_at_a_stop_still_give_the_scale(one_thread):
    """A clip that drives two pairs, then waits four with its poses still: the waiting frames differ
    only by sensor noise, and their fits move a few millimetres, above the 1 mm of a still pair.
    Their ratios of pose to image step, 0, were half the median's values: "no scale", though the
    poses are right (and poses still to rounding, ratios of 1e-14, a height "not in metres"). Now a pair whose poses stand still gives no scale, and the poses are refused
    only where such pairs move in the images at least half as far as the others: the height is the
    driving pairs'."""
    pairs = render_sequence("default", 2, size=(188, 621))
    cam = pairs[0]["camera"]
    g = torch.Generator().manual_seed(0)
    still = [pairs[-1]["image2"] + 1.9 * torch.randn(pairs[-1]["image2"].shape, generator=g) for _ in range(4)]
    frames = [p["image1"] for p in pairs] + [f.clamp(0, 255).round() for f in [pairs[-1]["image2"], *still]]
    poses = torch.stack([pairs[0]["pose1"], pairs[1]["pose1"], *[pairs[1]["pose2"]] * 5])
    options = dict(passes=1, keep_fits=False, max_points=1000)
    drive = fit_sequence(frames[:3], pairs[0]["road"], cam, poses=poses[:3], **options)
    seq = fit_sequence(frames, pairs[0]["road"], cam, poses=poses, **options)
    steps = torch.stack([seq.first_pass[n] for n in ("x_d", "y_d", "z_d")], -1).norm(dim=-1)
    assert bool(seq.success.all()) and int((steps[2:] > 1e-3).sum()) >= 2, steps  # (the noise "moves")
    assert bool((steps[2:] < 0.01).all()) and bool((steps[:2] > 1.0).all()), steps
    assert seq.calibrated_from == 2  # (the waiting pairs "move", but their images show no attitude)
    assert seq.mounting["height"] == pytest.approx(drive.mounting["height"], rel=1e-9)
    assert seq.mounting["height"] == pytest.approx(float(cam.height[0]), rel=0.1)
    # poses chained from a KITTI file's relative ones stand still only to rounding (steps of 4e-17 m):
    # their tiny ratios made the height 3e-14 m, refused as poses "not in metres"
    rounded = poses.clone()
    rounded[3:, 0, 3] += 4e-17 * torch.arange(1, 5, dtype=poses.dtype)
    seq = fit_sequence(frames, pairs[0]["road"], cam, poses=rounded, **options)
    assert seq.mounting["height"] == pytest.approx(drive.mounting["height"], rel=1e-9)


def test_fit_sequence_whose_fits_all_fail_keeps_the_input_mounting(one_thread):
    """Noise frames: no pair's fit succeeds, so nothing is calibrated: the input camera's roll and
    pitch stay (not a mean of failed fits), and with keep_fits the fits are still there."""
    p = render_pair("default", 0, size=(64, 160))
    g = torch.Generator().manual_seed(0)
    frames = [torch.rand(3, 64, 160, generator=g) * 255 for _ in range(3)]
    camera = p["camera"].replace(roll=0.01, pitch=-0.02)
    seq = fit_sequence(frames, p["road"], camera, keep_fits=True)
    assert seq.calibrated_from == 0 and not bool(seq.success.any())
    assert seq.mounting == {"roll": float(camera.roll[0]), "pitch": float(camera.pitch[0])}
    assert torch.equal(seq.camera.roll, camera.roll) and torch.equal(seq.camera.pitch, camera.pitch)
    assert len(seq.fits) == 2
    # the result's camera is its own (editing it leaves the caller's as it was)
    K = camera.K.clone()
    seq.camera.K.mul_(2.0)
    seq.camera.height.add_(1.0)
    assert torch.equal(camera.K, K) and torch.equal(camera.height, p["camera"].height)


def test_fit_sequence_pairs_that_do_not_move_calibrate_no_attitude(body_motion_clip, monkeypatch):
    """A stop (a frame repeated): without a translation the road's normal does not enter the pair's
    homography, and its fit's roll and pitch are where the prior put them, the input camera's. Such
    pairs once calibrated the mounting too, dragging it towards the input camera's; they count
    neither there nor as attitudes in the track (their rotation, the attitude change, does), and a
    clip that never moves calibrates nothing."""
    import fsof_torch.estimation.sequence as sequence

    pairs, frames, _ = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    sigmas = []

    def spy(attitude, change, attitude_sigma, change_sigma):
        sigmas.append((attitude_sigma.clone(), change_sigma.clone()))
        return smooth_attitude(attitude, change, attitude_sigma, change_sigma)

    monkeypatch.setattr(sequence, "smooth_attitude", spy)
    seq = fit_sequence([frames[0], frames[1], frames[1], frames[1], frames[2]], road, cam, keep_fits=False,
                       max_points=1000)
    moving = torch.tensor([True, False, False, True])
    steps = torch.stack([seq.first_pass[n] for n in ("x_d", "y_d", "z_d")], -1).norm(dim=-1)
    assert bool(seq.success.all()) and bool((steps[moving] > 0.5).all()) and bool((steps[~moving] < 1e-4).all())
    assert seq.calibrated_from == 2
    for name in ("roll", "pitch"):
        still = seq.first_pass[name][~moving]  # (the prior's mean: the input camera's attitude)
        torch.testing.assert_close(still, getattr(cam, name).double().expand(2), rtol=0, atol=1e-4)
        # of two moving pairs, their median: the mean of the two
        assert seq.mounting[name] == pytest.approx(float(seq.first_pass[name][moving].mean()), abs=1e-12)
    assert len(sigmas) == 2
    for attitude_sigma, change_sigma in sigmas:
        assert bool(torch.isinf(attitude_sigma[~moving]).all()) and bool(torch.isfinite(attitude_sigma[moving]).all())
        assert bool(torch.isfinite(change_sigma).all()) and torch.equal(change_sigma, change_sigma[:1].expand(4))
    # a clip that never moves: nothing calibrated, the input camera's mounting kept, no second pass
    still = fit_sequence([frames[0]] * 3, road, cam, keep_fits=False, max_points=1000)
    assert bool(still.success.all()) and still.calibrated_from == 0
    assert still.mounting == {"roll": float(cam.roll[0]), "pitch": float(cam.pitch[0])}
    assert len(sigmas) == 2


def test_fit_sequence_takes_changes_known_far_better_than_the_attitudes(monkeypatch):
    """body_rotation_deg=1e-9 (the body's pitch and roll change held all but rigid) stopped the clip
    after its first pass with a ZeroDivisionError in the track's solve, and attitude_deg=1e100 with
    torch's RuntimeError "value cannot be converted to type float without overflow" (its σ made a
    float32 tensor first). The track now follows the measured changes, and the σ are float64's."""
    import fsof_torch.estimation.sequence as sequence

    pairs = render_sequence("body-motion", 3, seed=0, size=(94, 310))
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    calls = []

    def spy(attitude, change, attitude_sigma, change_sigma):
        out = smooth_attitude(attitude, change, attitude_sigma, change_sigma)
        calls.append((change, attitude_sigma, change_sigma, out[0]))
        return out

    monkeypatch.setattr(sequence, "smooth_attitude", spy)
    for options in (dict(attitude_deg=1e100), dict(body_rotation_deg=1e-9)):
        calls.clear()
        seq = fit_sequence(frames, pairs[0]["road"], pairs[0]["camera"], keep_fits=False, max_points=800, **options)
        assert seq.calibrated_from == 3 and bool(seq.success.all()) and len(calls) == 2
        for change, attitude_sigma, change_sigma, track in calls:
            assert attitude_sigma.dtype == change_sigma.dtype == torch.float64
            assert float(attitude_sigma[0]) == math.radians(options.get("attitude_deg", 1.0))
            assert float(change_sigma[0]) == 0.1 * options.get("body_rotation_deg", 0.3) * (math.pi / 180)
            if "body_rotation_deg" in options:  # (σ_c 1.7e-12 rad: the track steps by the changes)
                torch.testing.assert_close(track.diff(), change, rtol=0, atol=1e-11)


def test_fit_sequence_pairs_that_creep_calibrate_no_attitude():
    """A vehicle creeping by about 4 mm a frame moves (its fits succeed, their translations well
    above the 1 mm of a stop), but its images fix the camera's attitude less well than the prior
    does: each fit's roll and pitch lie between the prior's and the truth, and once calibrated the
    mounting as if measured. Such pairs count neither for the mounting nor as attitudes in the
    track: the input camera's mounting stays."""
    pairs = render_sequence("body-motion", 2, seed=0, speed=0.04)
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    cam = pairs[0]["camera"]
    seq = fit_sequence(frames, pairs[0]["road"], cam, passes=1, max_points=1000)
    steps = torch.stack([seq.first_pass[n] for n in ("x_d", "y_d", "z_d")], -1).norm(dim=-1)
    assert bool(seq.success.all()) and bool((steps > 0.003).all()), steps
    deg = math.pi / 180
    for fit in seq.fits:  # (the prior's 1°: the images add less than it)
        for name in ("roll", "pitch"):
            i = list(fit.params).index(name)
            assert float(fit.covariance[0, i, i]) > 0.5 * deg ** 2
    assert float((seq.first_pass["pitch"] - float(cam.pitch[0])).abs().max()) > 0.05 * deg
    assert seq.calibrated_from == 0
    assert seq.mounting == {"roll": float(cam.roll[0]), "pitch": float(cam.pitch[0])}


def test_fit_sequence_keeping_the_fits_of_an_uncalibrated_clip_with_poses_changes_no_parameter():
    """A creeping clip with poses: nothing calibrates the attitude (so pass 1 stands), the poses
    give the height. keep_fits runs pass 1 again for its fits; it ran at the poses' height, where
    the priors in metres (the vertical motion's 2 cm, the carried motion's 5 cm) weigh otherwise:
    its z_d differed from keep_fits=False's by up to 0.3 % and its pitch by 1e-5 rad. Now both are
    pass 1's parameters with the translations rescaled to that height, and the fits hold them."""
    pairs = render_sequence("body-motion", 2, seed=0, speed=0.04, size=(188, 621))
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    poses = torch.stack([p["pose1"] for p in pairs] + [pairs[-1]["pose2"]])
    cam = pairs[0]["camera"]
    kept, lean = (fit_sequence(frames, pairs[0]["road"], cam, poses=poses, max_points=1000, keep_fits=keep)
                  for keep in (True, False))
    assert kept.calibrated_from == lean.calibrated_from == 0 and bool(kept.success.all())
    ratio = kept.mounting["height"] / float(cam.height[0])
    assert kept.mounting == lean.mounting and abs(ratio - 1) > 0.01
    for name, first in kept.first_pass.items():
        metric = first * ratio if name in ("x_d", "y_d", "z_d") else first
        assert torch.equal(kept.params[name], lean.params[name]), name
        torch.testing.assert_close(kept.params[name], metric, rtol=1e-6, atol=0)  # (scaled in float32)
        torch.testing.assert_close(kept.params[name], torch.cat([f.params[name] for f in kept.fits]).double(),
                                   rtol=1e-6, atol=1e-9)
    assert all(float(f.camera.height[0]) == pytest.approx(kept.mounting["height"]) for f in kept.fits)


def test_fit_sequence_weighs_each_pairs_attitude_by_its_precision():
    """A clip that drives at 12 m/s, then creeps at 0.3 m/s (3 cm a frame: it moves, and its fits'
    attitudes are known to a few tenths of a degree rather than a few hundredths). Averaged alike,
    the creeping pairs drew the mounting 0.3° towards the nominal; weighted by their precision
    (the inverse of their posterior variance) it is the moving pairs' attitude."""
    from fsof_torch.estimation.sequence import _robust_mean

    fast = render_sequence("body-motion", 4, seed=0, speed=12.0)
    slow = render_sequence("body-motion", 4, seed=0, speed=0.3)
    frames = [p["image1"] for p in fast] + [fast[-1]["image2"]] + [p["image1"] for p in slow] + [slow[-1]["image2"]]
    cam = fast[0]["camera"]
    seq = fit_sequence(frames, fast[0]["road"], cam, passes=1, max_points=2000)
    deg = math.pi / 180
    truth = float(np.mean([p["plane"]["pitch"] for p in fast]))
    assert bool(seq.success.all()) and seq.calibrated_from == 9
    assert abs(_robust_mean(seq.first_pass["pitch"], seq.success) - truth) > 0.2 * deg  # (averaged alike)
    assert abs(seq.mounting["pitch"] - truth) < 0.1 * deg
    assert abs(float(cam.pitch[0]) - truth) > 0.8 * deg  # (the nominal: what the creeping pairs lean to)


def test_fit_sequence_holds_fixed_attitude_parameters_in_both_passes(body_motion_clip):
    """``fixed`` (a fit_image option) holds parameters at the start. The second pass started the
    attitude at the smoothed track, so it held them there: a held roll changed from pair to pair,
    a held pitch change was not 0. They stay where the first pass held them: the camera's roll
    (the mounting calibrated from it) and no change."""
    pairs, frames, _ = body_motion_clip
    cam = pairs[0]["camera"]
    seq = fit_sequence(frames[:4], pairs[0]["road"], cam, fixed=("roll", "pitch_change"), keep_fits=False,
                       max_points=1000)
    assert bool(seq.success.all()) and seq.calibrated_from == 3
    assert seq.mounting["roll"] == float(cam.roll[0])
    for got in (seq.first_pass, seq.params):
        assert torch.equal(got["roll"], cam.roll.double().expand(3))
        assert torch.equal(got["pitch_change"], torch.zeros(3, dtype=torch.float64))
    # the free attitude was fitted again, at the smoothed track
    assert not torch.equal(seq.params["pitch"], seq.first_pass["pitch"])


def test_fit_sequence_refuses_poses_whose_height_is_not_in_metres(body_motion_clip):
    """Poses in millimetres (or kilometres) gave a camera height of 1650 m (1.65 mm) and translations
    in those units, reported as calibrated: a height more than 10 times the camera's either way is
    no metric scale, and stops the fit naming ``poses``."""
    pairs, frames, poses = body_motion_clip
    # (in millimetres the steps stop it first: more than a vehicle travels between two frames)
    for scale, shown in ((30.0, r"\d+\.\d+ m, \d+(\.\d+)? times"), (1e-3, r"0\.0016\d+ m, 0\.001 times")):
        wrong = poses[:3].clone()
        wrong[:, :3, 3] *= scale
        with pytest.raises(ValueError, match=rf"^poses: their translations give a camera height of {shown} the "
                                             r"camera's 1\.65 m \(more than 10 times either way\)"):
            fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], poses=wrong, passes=1, max_points=500)
    wrong = poses[:3].clone()
    wrong[:, :3, 3] *= 1000.0
    with pytest.raises(ValueError, match=r"^poses: the pose of frames\[0\] and the pose of frames\[1\] lie .*millimetres"):
        fit_sequence(frames[:3], pairs[0]["road"], pairs[0]["camera"], poses=wrong, passes=1, max_points=500)


def test_fit_sequence_refuses_poses_that_are_not_rigid_before_reading_a_frame(body_motion_clip, monkeypatch):
    """Only the poses' translations are used, and poses that were no rigid transforms passed: transposed
    poses (their translations in the bottom row, the last column 0 0 0 1) fitted the whole first pass
    and then said "their translations give no scale (camera height 0 m)", and a rotation block scaled
    by 2 was taken as a pose. Now either is a ValueError naming ``poses`` and the pose, before a fit."""
    pairs, frames, poses = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    import fsof_torch.estimation.sequence as S

    def no_fit(*args, **kwargs):
        raise AssertionError("a pair was fitted")

    monkeypatch.setattr(S, "fit_image", no_fit)
    scaled = poses[:3].clone()
    scaled[1, :3, :3] *= 2.0
    cases = ((poses[:3].transpose(1, 2), r"sample 0: its bottom row is \[.*\], not 0 0 0 1 \(a transposed pose"),
             (scaled, r"sample 1: its 3×3 block is not a rotation: \|RᵀR − I\| up to 3, det R = 8"))
    for wrong, what in cases:
        with pytest.raises(ValueError, match=rf"^poses: expected rigid transforms .*got {what}"):
            fit_sequence(frames[:3], road, cam, poses=wrong, max_points=500)


def test_fit_sequence_names_an_attitude_deg_too_large_for_the_track_before_a_fit(body_motion_clip, monkeypatch):
    """attitude_deg is the smoothed track's attitude σ too, weighed by 1 / σ² in float64: at 1e200 degrees
    that weight is 0, and after a whole first pass smooth_attitude stopped the clip naming its own
    attitude_sigma, an argument the caller never gave. Now a ValueError names attitude_deg before any
    fit; with one pass, which makes no track, the value stands (a prior that weighs nothing)."""
    pairs, frames, _ = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    import fsof_torch.estimation.sequence as S

    def no_fit(*args, **kwargs):
        raise AssertionError("a pair was fitted")

    with monkeypatch.context() as m:
        m.setattr(S, "fit_image", no_fit)
        for value in (1e156, 1e200, 1.5e308):
            with pytest.raises(ValueError, match=rf"^attitude_deg: expected a standard deviation whose weight 1 / σ² "
                                                 rf"in radians is above 0 in float64 .*got {re.escape(repr(value))}$"):
                fit_sequence(frames[:3], road, cam, attitude_deg=value, max_points=500)
    seq = fit_sequence(frames[:3], road, cam, attitude_deg=1e200, passes=1, max_points=500)
    assert seq.params["z_d"].shape == (2,) and bool(torch.isfinite(seq.params["z_d"]).all())
    # the largest that weighs: the track is made
    seq = fit_sequence(frames[:3], road, cam, attitude_deg=7e155, max_points=500)
    assert seq.calibrated_from > 0 and bool(torch.isfinite(seq.params["pitch"]).all())


def test_fit_sequence_carries_no_motion_prior_out_of_a_pair_that_did_not_move(body_motion_clip):
    """A frame repeated (a recording's glitch) stands still for one pair; the next pair then steps
    two frames. The previous motion, carried as a prior (0 ± 5 cm after the still pair), held that
    step at about 0 (frames 1, 1, 3: z_d -0.016 m for 2.4 m, reported as a success) and, through
    the next prior, bent the pair after it too (frames 0, 0, 2, 3: 0.06 m, then 0.92 m at -4.8° of
    pitch for 1.2 m). After a still pair no motion prior is carried: each step is fitted as alone."""
    pairs, frames, poses = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    for order in ([0, 1, 1, 3], [0, 0, 2, 3]):
        seq = fit_sequence([frames[i] for i in order], road, cam, passes=1, keep_fits=False, max_points=1000)
        assert bool(seq.success.all())
        steps = (poses[order[1:], :3, 3] - poses[order[:-1], :3, 3]).norm(dim=-1)  # (metres: about 1.2 a frame)
        torch.testing.assert_close(seq.params["z_d"], steps, rtol=0.05, atol=1e-3)


def test_fit_sequence_fits_a_pair_alone_where_its_images_contradict_the_carried_motion(body_motion_clip):
    """A dropped frame doubles a step (or triples it): the previous motion, carried as a prior
    (1.2 ± 0.17 m), held frames 2 → 4 at 2.14 m for 2.4 m with 0.7° more pitch, and frames 1 → 4
    at 2.41 m for 3.6 m, both reported as successes. A fit that lies more than 3 σ from the carried
    motion (or fails under it) is fitted again without it."""
    pairs, frames, poses = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    for order in ([0, 1, 2, 4], [0, 1, 4]):
        seq = fit_sequence([frames[i] for i in order], road, cam, passes=1, keep_fits=False, max_points=1000)
        assert bool(seq.success.all())
        steps = (poses[order[1:], :3, 3] - poses[order[:-1], :3, 3]).norm(dim=-1)
        torch.testing.assert_close(seq.params["z_d"], steps, rtol=0.05, atol=1e-3)


def test_fit_sequence_makes_its_tensors_on_the_frames_device():
    """With the frames on a GPU, the pairs' bookkeeping made on the CPU (torch's default device)
    met the fits' tensors: torch's "Expected all tensors to be on the same device" after the first
    pass (``ok & (image_steps > ...)``, the poses' steps, a carried prior's float sigma). Emulated
    here: every tensor that sequence.py makes without naming a device lands on the meta device (as
    on a GPU it would land on the CPU), where mixing it with the frames' tensors, or reading it, is
    an error. The results are the same as without the emulation."""
    import sys

    from torch.overrides import TorchFunctionMode

    from fsof_torch.estimation import sequence

    constructors = {torch.tensor, torch.as_tensor, torch.zeros, torch.ones, torch.empty, torch.full, torch.arange,
                    torch.linspace, torch.eye, torch.rand, torch.randn, torch.randint}

    class DefaultDeviceElsewhere(TorchFunctionMode):
        def __init__(self):
            super().__init__()
            self.made = []

        def __torch_function__(self, func, types, args=(), kwargs=None):
            kwargs = dict(kwargs or {})
            if func in constructors and kwargs.get("device") is None:
                caller = sys._getframe(1)
                if caller.f_code.co_filename == sequence.__file__:
                    self.made.append(caller.f_lineno)
                    kwargs["device"] = "meta"
            return func(*args, **kwargs)

    pairs = render_sequence("body-motion", 3, seed=0, size=(94, 310))
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    poses = torch.stack([p["pose1"] for p in pairs] + [pairs[-1]["pose2"]])
    roads, cam = [p["road"] for p in pairs], pairs[0]["camera"]
    plain = fit_sequence(frames, roads, cam, poses=poses)
    assert plain.calibrated_from == 3 and "height" in plain.mounting  # (both passes and the poses' scale ran)
    with DefaultDeviceElsewhere() as mode:
        seq = fit_sequence(frames, roads, cam, poses=poses)
    assert mode.made == []
    assert seq.mounting == plain.mounting and torch.equal(seq.success, plain.success)
    assert all(torch.equal(seq.params[n], plain.params[n]) for n in plain.params)
    assert {t.device.type for t in (*seq.params.values(), *seq.first_pass.values(), seq.success)} == {"cpu"}


def test_fit_sequence_names_a_frame_mask_flow_or_poses_without_values_by_its_index(body_motion_clip):
    """A frame, mask or flow on the meta device (or on another device than ``frames[0]``) was named
    by fit_image's argument it went into: ``image2`` for frames[2] (the second pair's second frame),
    ``mask`` for mask[1], ``flow`` for flows[1]; poses on the meta device were torch's RuntimeError
    "Tensor.item() cannot be called on meta tensors". Each is now named as the clip's item, before
    any fit."""
    from fsof_torch.estimation.sequence import _item

    pairs, frames, poses = body_motion_clip
    cam, road = pairs[0]["camera"], pairs[0]["road"]
    meta = torch.device("meta")
    no_values = "a tensor on the meta device has shapes but no values"
    for k in (0, 1, 2):
        clip = [f.to(meta) if i == k else f for i, f in enumerate(frames[:3])]
        with pytest.raises(ValueError, match=rf"^frames\[{k}\]: {no_values} to fit"):
            fit_sequence(clip, road, cam, max_points=500)
    with pytest.raises(ValueError, match=rf"^mask\[1\]: {no_values} to fit"):
        fit_sequence(frames[:3], [road, road.to(meta)], cam, max_points=500)
    with pytest.raises(ValueError, match=rf"^mask: {no_values} to fit"):
        fit_sequence(frames[:3], road.to(meta), cam, max_points=500)
    with pytest.raises(ValueError, match=rf"^flows\[1\]: {no_values} to fit"):
        fit_sequence(frames[:3], road, cam, flows=[pairs[0]["flow"], pairs[1]["flow"].to(meta)], max_points=500)
    with pytest.raises(ValueError, match=rf"^poses: {no_values} to give the clip's translations their scale"):
        fit_sequence(frames[:3], road, cam, poses=poses[:3].to(meta))
    # an item on another device than frames[0] (a GPU's frame beside CPU ones; emulated: the clip on meta)
    with pytest.raises(ValueError, match=r"^frames\[1\]: expected the device of frames\[0\] \(meta\), got cpu$"):
        _item(frames[1], "frames[1]", "an image", (3,), tuple(frames[1].shape[-2:]), meta)


def test_a_failed_pairs_fitted_change_does_not_move_the_attitude_track():
    """A failed fit's attitude change is no measurement: its value may be anything within the bounds
    (5°). It entered the track loosely (10 × body_rotation_deg) but at its value: in a clip of 6
    pairs whose attitudes all read 0.5° and whose other changes 0, a failed pair's 5° split the
    track into 0.33° before it and 0.75° after, and pass 2 was tied to that. Now it counts as no
    change (still loosely, linking the frames on either side): the track is 0.5° throughout."""
    from fsof_torch.estimation.sequence import _track

    deg = math.pi / 180
    N = 6
    params = {n: torch.full((N,), 0.5 * deg, dtype=torch.float64) for n in ("roll", "pitch")}
    params.update({n: torch.zeros(N, dtype=torch.float64) for n in ("roll_change", "pitch_change")})
    params["pitch_change"][3] = 5 * deg
    params["roll_change"][3] = -5 * deg
    ok = torch.ones(N, dtype=torch.bool)
    ok[3] = False
    track = _track(params, ok, ok, 1.0, 0.3)
    for name in ("roll", "pitch"):
        value, sigma = track[name]
        torch.testing.assert_close(value, torch.full((N + 1,), 0.5 * deg, dtype=torch.float64), rtol=0, atol=1e-12)
        assert bool((sigma > 0).all()) and bool((sigma < 1 * deg).all())
    # (a pair that succeeded measures its change, as before: the track steps by it)
    ok[3] = True
    stepped = _track(params, ok, ok, 1.0, 0.3)["pitch"][0]
    assert float(stepped[4] - stepped[3]) == pytest.approx(5 * deg, rel=0.01)
