#!/usr/bin/env python3
"""The grasp check (`moma.grasp_check`, PROXY scores) of later frames under calibrations laid out
as `sigma_by_sample_distance.py` writes them: does `success_prob` follow what the grasps achieve?

For each opaque shared set, SIMULATED predictions (simulator seeds 0–2), SSRA, GSSA and LWLR, and
each calibration directory given (e.g. the same run's calibrations from two moma builds), every
frame after the first is aligned one-shot by the calibration, its top-10 grasps planned within
the frame's object mask (robust, the calibration's error model) and executed on the frame's
ground truth by the proxy's rules.  Printed per set, gripper and directory: grasps, successes,
the achieved rate, the mean `success_prob`, and their gap (mean probability − rate, pooled over
methods, seeds and frames).

    python3 benches/grasp/grasp_check_by_calibration.py ../shared DIR [DIR ...]

DIR is the OUT of `sigma_by_sample_distance.py` (…/SET/simK/*.npy, …/SET/simK.METHOD.json).
Needs numpy and the moma Python package.
"""

import json
import os
import sys

import numpy as np

import moma

SETS = ["gqcnn-primesense", "graspnet6dof-table", "m2t2-table"]
METHODS = ["ssra", "gssa", "lwlr"]
SIM_SEEDS = [0, 1, 2]
GRIPPERS = ["suction", "parallel"]


def main(shared, dirs):
    print("SIMULATED predictions, PROXY scores: top-10 grasps of the frames after the first, "
          "per calibration directory\n")
    print("| set | gripper | calibrations | grasps | successes | rate | mean success_prob | gap |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for name in SETS:
        set_dir = f"{shared}/data/{name}"
        frames = sorted(os.listdir(f"{set_dir}/frames"))[1:]
        truths = {f: np.asarray(moma.read_depth(f"{set_dir}/frames/{f}/depth.png")) for f in frames}
        masks = {f: np.asarray(moma.read_mask(f"{set_dir}/frames/{f}/mask.png"), dtype=bool)
                 for f in frames if os.path.exists(f"{set_dir}/frames/{f}/mask.png")}
        for gripper in GRIPPERS:
            for d in dirs:
                grasps = successes = 0
                prob_sum = 0.0
                for seed in SIM_SEEDS:
                    for method in METHODS:
                        cal = moma.Calibration.load(f"{d}/{name}/sim{seed}.{method}.json")
                        for f in frames:
                            pred = np.load(f"{d}/{name}/sim{seed}/{f}.npy")
                            c = moma.grasp_check(cal, pred, truths[f], gripper=gripper,
                                                 mask=masks.get(f), seed=0)
                            grasps += c["grasps"]
                            successes += c["successes"]
                            if c["mean_success_prob"] is not None:
                                prob_sum += c["mean_success_prob"] * c["grasps"]
                rate = successes / grasps if grasps else float("nan")
                prob = prob_sum / grasps if grasps else float("nan")
                print(f"| {name} | {gripper} | {d} | {grasps} | {successes} | {rate:.3f} | "
                      f"{prob:.3f} | {prob - rate:+.3f} |")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2:])
