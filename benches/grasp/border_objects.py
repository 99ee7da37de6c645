#!/usr/bin/env python3
"""Where do grasps planned without a mask land? (the border rule of `moma grasp`, docs/grasping.md)

For every frame of each set with a mask.png: plans the top-5 grasps on the frame's ground-truth
depth without --mask, once with the default (regions touching the image border are not objects)
and once with --keep-border-objects (the behaviour before the rule), projects each planned point
(suction) or grasp centre (parallel) into the image and counts it "on an object" when it falls
within 5 px of a mask pixel. Ground-truth depth: no depth model is involved. Standard library
only (a small PNG reader for 8-bit masks).

    python3 benches/grasp/border_objects.py --moma target/release/moma --shared ../shared \
        gqcnn-primesense graspnet6dof-table m2t2-table cleargrasp-transparent
"""

import argparse
import json
import os
import struct
import subprocess
import zlib


def read_png_grey(path):
    """8-bit PNG (grey, grey+alpha, RGB or RGBA; non-interlaced): rows of the first channel."""
    data = open(path, "rb").read()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    pos, idat = 8, b""
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
        elif kind == b"IDAT":
            idat += body
    if depth != 8:
        raise ValueError(f"{path}: {depth}-bit PNG, expected 8-bit")
    bpp = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
    raw, stride = zlib.decompress(idat), w * bpp
    rows, prev, i = [], bytearray(stride), 0
    for _ in range(h):
        f, line = raw[i], bytearray(raw[i + 1:i + 1 + stride])
        i += 1 + stride
        for x in range(stride):
            a = line[x - bpp] if x >= bpp else 0
            b, c = prev[x], (prev[x - bpp] if x >= bpp else 0)
            if f == 1:
                line[x] = (line[x] + a) & 255
            elif f == 2:
                line[x] = (line[x] + b) & 255
            elif f == 3:
                line[x] = (line[x] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line[0::bpp]))
        prev = line
    return w, h, rows


def on_objects(moma, set_dir, frame, gripper, keep, near_px=5):
    cam = json.load(open(f"{set_dir}/camera.json"))
    args = [moma, "grasp", "--depth", f"{set_dir}/frames/{frame}/depth.png", "--camera",
            f"{set_dir}/camera.json", "--gripper", gripper, "--top", "5", "--json"]
    if keep:
        args.append("--keep-border-objects")
    out = subprocess.run(args, capture_output=True, text=True, check=True)
    grasps = json.loads(out.stdout)
    w, h, mask = read_png_grey(f"{set_dir}/frames/{frame}/mask.png")
    hits = 0
    for g in grasps:
        x, y, z = g.get("point_m") or g["center_m"]
        u = round(cam["fx"] * x / z + cam["cx"])
        v = round(cam["fy"] * y / z + cam["cy"])
        hits += any(0 <= v + dv < h and 0 <= u + du < w and mask[v + dv][u + du]
                    for dv in range(-near_px, near_px + 1)
                    for du in range(-near_px, near_px + 1))
    return hits, len(grasps)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--moma", default="target/release/moma")
    p.add_argument("--shared", default="../shared")
    p.add_argument("sets", nargs="+")
    args = p.parse_args()
    print("| set | gripper | on objects, --keep-border-objects (before) | on objects, default |")
    print("|---|---|---|---|")
    for name in args.sets:
        d = os.path.join(args.shared, "data", name)
        frames = [f for f in sorted(os.listdir(f"{d}/frames"))
                  if os.path.exists(f"{d}/frames/{f}/mask.png")]
        for gripper in ["suction", "parallel"]:
            tally = {True: [0, 0], False: [0, 0]}
            for f in frames:
                for keep in (True, False):
                    hit, n = on_objects(args.moma, d, f, gripper, keep)
                    tally[keep][0] += hit
                    tally[keep][1] += n
            print(f"| {name} | {gripper} | {tally[True][0]} / {tally[True][1]} | "
                  f"{tally[False][0]} / {tally[False][1]} |", flush=True)


if __name__ == "__main__":
    main()
