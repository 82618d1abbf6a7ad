"""How the default refiner fails safe, measured: dark and noisy frames, identical frames, a car
inside the road mask; and where it does not: a plain road without noise.

1. Dark frames: the shared KITTI pair's images × gain plus Gaussian noise (σ grey levels), DIS on
   them, through ``FreespaceRefiner()`` with the images: whether the image fit succeeded and the
   correlation of the images' detail under its motion, whether the pair was refined, what the gate
   found (informative, confirmed), the road end-point error of DIS, of the model flow and of
   the output against the KITTI ground truth, and the time of DIS and of the refiner (median of
   three calls): a frame whose image fit fails tries every way on before giving up.
2. Identical frames (a stopped car): the synthetic scene's image 1 twice; the estimated motion.
3. A car inside the mask: the synthetic default scene's pairs 0, 5, 10 with the moving objects'
   pixels added to the road mask, DIS as the prediction: the share of car pixels whose flow
   changed, and the cars' and the road's end-point error before and after.
4. A plain road: the synthetic default scene's pair 0 with its asphalt's texture at a tenth and
   a fifth of its contrast, driving straight 0.3, 0.6 and 1.2 m a frame, noise-free and with
   1 grey level of Gaussian noise; a good prediction (the true flow × 1.05): whether the pair was
   refined, the image fit's forward motion (refined or not), the road end-point error before and after.

    python benchmarks/failsafe.py

One thread; needs ``../shared`` for part 1.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI15 = ("image_10.png", "image_11.png", "flow_noc_10.png", "road.json", "calib_cam_to_cam.txt")


def dis(image1, image2):
    from refine.sources import dis_flow

    return dis_flow(image1, image2)


def main(argv: list[str] | None = None) -> int:
    from cli import description, median_ms, present

    argparse.ArgumentParser(description=description(__doc__)).parse_args(argv)
    import fsof_torch as fs
    from fsof_torch.data.scene import render_pair

    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    refiner = fs.FreespaceRefiner()
    k15 = SHARED / "kitti15_000000"
    if present(k15, KITTI15, "KITTI pair kitti15_000000 (part 1, dark frames)"):
        im1, im2 = fs.read_image(k15 / "image_10.png"), fs.read_image(k15 / "image_11.png")
        gt, valid = fs.read_kitti_flow(k15 / "flow_noc_10.png")
        road = fs.read_road_mask(k15 / "road.json", size=tuple(im1.shape[-2:]))
        cam = fs.Camera.from_kitti(k15 / "calib_cam_to_cam.txt", cam=2, height=1.65)
        m = road[0] & valid.reshape(road.shape[-2:]).bool()
        epe = lambda f: float((f - gt).norm(dim=0)[m].mean())  # noqa: E731
        print("Dark frames (KITTI pair × gain + noise σ):\n")
        print("| gain | σ | fit success | correlation | refined | informative | confirmed | census model / DIS "
              "| EPE DIS | EPE model | EPE out | time DIS / refiner (ms) |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for gain, sigma in ((1.0, 0.0), (0.2, 2.0), (0.2, 5.0), (0.1, 5.0), (0.05, 5.0)):
            g = torch.Generator().manual_seed(0)
            d1 = (im1 * gain + sigma * torch.randn(im1.shape, generator=g)).clamp(0, 255)
            d2 = (im2 * gain + sigma * torch.randn(im2.shape, generator=g)).clamp(0, 255)
            f = dis(d1, d2)
            out = refiner(f[None], road[None], cam, images=(d1[None], d2[None]))
            t_dis = median_ms(lambda: dis(d1, d2))
            t_ref = median_ms(lambda: refiner(f[None], road[None], cam, images=(d1[None], d2[None])))
            gate, fit = out.gate, out.fit
            # (where the image fit failed, the gate judges nothing)
            judged = (f"{float(gate.cost_model[0]):.3f} / {float(gate.cost_prediction[0]):.3f}"
                      if int(gate.points[0]) else "not judged")
            print(f"| {gain} | {sigma} | {bool(fit.success[0])} | {float(fit.extras['correlation'][0]):.2f} | "
                  f"{bool(out.refined[0])} | {bool(gate.informative[0])} | {bool(gate.confirmed[0])} | "
                  f"{judged} | {epe(f):.2f} | "
                  f"{epe(out.flow_model[0]):.2f} | {epe(out.flow[0]):.2f} | {t_dis:.0f} / {t_ref:.0f} |")
    p = render_pair("default", 5, seed=0)
    image = p["image1"][None]
    out = refiner(torch.zeros(1, 2, *image.shape[-2:]), p["road"][None], p["camera"], images=(image, image))
    motion = {k: round(float(v[0]), 6) for k, v in out.odometry.items()}
    print(f"\nIdentical frames: refined {bool(out.refined[0])}, motion {motion}")
    print("\nA car inside the mask (synthetic default scene, DIS):\n")
    print("| pair | car pixels | car pixels changed | car EPE before / after | road EPE before / after |")
    print("|---|---|---|---|---|")
    for index in (0, 5, 10):
        p = render_pair("default", index, seed=0)
        car = p["moving"][0]
        mask = (p["road"] | p["moving"])[None]
        f = dis(p["image1"], p["image2"])
        out = refiner(f[None], mask, p["camera"], images=(p["image1"][None], p["image2"][None]))
        valid = p["valid"][0]
        e0, e1 = (f - p["flow"]).norm(dim=0), (out.flow[0] - p["flow"]).norm(dim=0)
        changed = float(((out.flow[0] - f).norm(dim=0)[car] > 0.01).float().mean())
        r = p["road"][0] & valid
        print(f"| {index} | {int(car.sum())} | {100 * changed:.0f} % | {float(e0[car & valid].mean()):.2f} / "
              f"{float(e1[car & valid].mean()):.2f} | {float(e0[r].mean()):.2f} / {float(e1[r].mean()):.2f} |")
    print("\nA plain road (synthetic default scene, pair 0, the true flow × 1.05 as the prediction):\n")
    print("| texture | forward m / frame | noise σ | refined | image fit's forward m | road EPE before / after |")
    print("|---|---|---|---|---|---|")
    for texture in (0.1, 0.2):
        for z_d in (0.3, 0.6, 1.2):
            p = render_pair("default", 0, seed=0, texture=texture, x_d=0.0, z_d=z_d, yaw=0.0)
            r = p["road"][0] & p["valid"][0]
            prediction = 1.05 * p["flow"]
            for sigma in (0.0, 1.0):
                g = torch.Generator().manual_seed(0)
                i1, i2 = ((p[k] + sigma * torch.randn(p[k].shape, generator=g)).clamp(0, 255)[None]
                          for k in ("image1", "image2"))
                out = refiner(prediction[None], p["road"][None], p["camera"], images=(i1, i2))
                e0, e1 = ((f - p["flow"]).norm(dim=0)[r].mean() for f in (prediction, out.flow[0]))
                print(f"| {texture} | {z_d} | {sigma:g} | {bool(out.refined[0])} | "
                      f"{round(float(out.fit.z_d[0]), 2) + 0.0:.2f} | {float(e0):.2f} / {float(e1):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
