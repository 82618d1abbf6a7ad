"""Road motion of a synthetic clip with body motion from its images alone: per-pair image fits
against fit_sequence (the mounting calibrated over the clip, the motion carried forward, the
attitude track smoothed), on the ``body-motion`` preset (or ``--preset NAME``) whose road flow and
attitude are exact (on the graded ``crest`` and ``dip`` the attitude is over the road under the
wheels, and no plane is the whole road).

Prints, per pair, the road end-point error (px, valid road pixels) of the single-pair fit
(``fit_image`` at the nominal camera) and of the clip's fit, and the error of the camera's pitch
and roll relative to the road (degrees) of the clip's fit; then the means and the calibrated
mounting against the clip's mean attitude, and the time per pair (single thread).

    python benchmarks/sequence_synthetic.py [--preset body-motion] [--pairs 8] [--seed 0] [--options '{"highpass": null}']

``--options`` passes keyword arguments of ``fit_image`` (JSON) to both fits.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from fsof_torch import PRESETS


def main(argv: list[str] | None = None) -> int:
    from cli import check_options, description, json_object, pair_count, scene_seed, thread_count

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--preset", default="body-motion", choices=PRESETS,
                        help="the synthetic scene (default body-motion)")
    parser.add_argument("--pairs", type=pair_count(), default=8, help="pairs of the clip (default 8)")
    parser.add_argument("--seed", type=scene_seed, default=0, help="the scene's seed, in [0, 2**62) (default 0)")
    parser.add_argument("--options", type=json_object, default={}, metavar="JSON",
                        help="fit_image keyword arguments as a JSON object (not those the script or "
                             "fit_sequence sets: the images, mask, camera, init, starts, prior)")
    parser.add_argument("--threads", type=thread_count, default=1,
                        help="torch and OpenCV threads, at most this machine's CPUs (default 1)")
    args = parser.parse_args(argv)
    from fsof_torch import fit_image, fit_sequence

    # (the options go to both fits; fit_sequence sets these itself)
    check_options(parser, args.options, "--options", fit_image,
                  reserved=("image1", "image2", "mask", "camera", "init", "starts", "prior"))
    import cv2

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    options = args.options

    from fsof_torch.data.scene import render_sequence

    pairs = render_sequence(args.preset, args.pairs, seed=args.seed, progress=True)
    print(f"preset {args.preset}, {args.pairs} pairs, seed {args.seed}")
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    camera = pairs[0]["camera"]
    t = time.perf_counter()
    single = [fit_image(p["image1"][None], p["image2"][None], p["road"][None], camera, **options) for p in pairs]
    t_single = (time.perf_counter() - t) / len(pairs)
    t = time.perf_counter()
    seq = fit_sequence(frames, [p["road"] for p in pairs], camera, progress=True, **options)
    t_seq = (time.perf_counter() - t) / len(pairs)

    deg = 180 / math.pi
    rows = []
    print(f"{'pair':>4} {'single EPE':>10} {'clip EPE':>9} {'pitch err':>9} {'roll err':>9}")
    for k, p in enumerate(pairs):
        road = (p["road"] & p["valid"])[0]
        e1 = float((single[k].flow[0] - p["flow"]).norm(dim=0)[road].mean())
        e2 = float((seq.fits[k].flow[0] - p["flow"]).norm(dim=0)[road].mean())
        dp = (float(seq.params["pitch"][k]) - p["plane"]["pitch"]) * deg
        dr = (float(seq.params["roll"][k]) - p["plane"]["roll"]) * deg
        rows.append((e1, e2, abs(dp), abs(dr)))
        print(f"{k:4d} {e1:10.3f} {e2:9.3f} {dp:+9.3f} {dr:+9.3f}")
    a = np.array(rows)
    print(f"mean {a[:, 0].mean():10.3f} {a[:, 1].mean():9.3f} {a[:, 2].mean():9.3f} {a[:, 3].mean():9.3f}  (|error|)")
    true_pitch = np.mean([p["plane"]["pitch"] for p in pairs]) * deg
    true_roll = np.mean([p["plane"]["roll"] for p in pairs]) * deg
    print(f"calibrated mounting: pitch {seq.mounting['pitch'] * deg:+.3f} deg (clip mean {true_pitch:+.3f}), "
          f"roll {seq.mounting['roll'] * deg:+.3f} deg (clip mean {true_roll:+.3f}); nominal pitch "
          f"{float(camera.pitch) * deg:+.3f}, roll {float(camera.roll) * deg:+.3f}")
    print(f"time per pair: single fit {t_single * 1e3:.0f} ms, clip (two passes) {t_seq * 1e3:.0f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
