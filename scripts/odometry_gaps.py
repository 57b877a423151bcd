"""Does the odometry stream measure the motion? Its predicted step length for frame pairs 0, 1, 2, ... frames apart.

For the first ``--frames`` frames of the first sequence of a dataset split, every pair ``(i, i + gap)`` goes
through the odometry stream (the trunk and the stream's own layers, eval mode, float32). A stream that measures
the motion predicts ~0 m for a frame paired with itself and steps that grow with the gap and follow the true
ones within a gap (correlation near 1); one that learnt the training speeds predicts about the same step
whatever the gap. Usage::

    .venv/bin/python scripts/odometry_gaps.py --checkpoint models/vlocnetpp_lite.safetensors --data runs/shipped/campus
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from vlocnetpp_core.data.dataset import open_dataset
from vlocnetpp_core.inference.checkpoint import load_checkpoint
from vlocnetpp_core.inference.network_input import image_tensor
from vlocnetpp_core.inference.preprocess import resize_image


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="NAME.safetensors with an odometry stream")
    p.add_argument("--data", required=True, help="dataset folder (DeepLoc layout or 7-Scenes)")
    p.add_argument("--split", default="train", help="split (default: train)")
    p.add_argument("--frames", type=int, default=120, help="frames from the start of the first sequence (default 120)")
    p.add_argument("--max-gap", type=int, default=4, help="largest gap in frames (default 4)")
    args = p.parse_args()
    torch.set_grad_enabled(False)
    model, _ = load_checkpoint(args.checkpoint)
    index = open_dataset(args.data, split=args.split)
    first = index.sequences[0]
    n = min(args.frames, len(first))
    frames = [index.load(i, depth=False, labels=False) for i in first[:n]]
    images = torch.cat([image_tensor(resize_image(f.image, model.config.input_size)) for f in frames])
    t_wc = np.stack([f.t for f in frames])
    features = model.step(images, tasks=("vo",))[0].taps["odo_res4"]  # each frame's Siamese Res4 (n, C4, H/16, W/16)
    pairs = n - args.max_gap
    print(f"{args.checkpoint} on {args.data} ({args.split}, frames {first[0]}..{first[0] + n - 1})")
    print("| gap [frames] | true step [m] | predicted step [m] | correlation within the gap |")
    print("|---|---|---|---|")
    for gap in range(args.max_gap + 1):
        xyz, _, _ = model.odometry(features[:pairs], features[gap : gap + pairs])
        predicted = xyz.norm(dim=1).numpy()
        true = np.linalg.norm(t_wc[gap : gap + pairs] - t_wc[:pairs], axis=1)
        corr = f"{np.corrcoef(true, predicted)[0, 1]:.2f}" if gap else "-"
        print(f"| {gap} | {true.mean():.2f} | {predicted.mean():.2f} +- {predicted.std():.2f} | {corr} |")


if __name__ == "__main__":
    main()
