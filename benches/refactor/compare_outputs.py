#!/usr/bin/env python3
"""Byte-for-byte comparison of what two `moma` binaries write on the shared sets (issue 24: a
refactoring must not change aligned depth, grasps, point clouds or evaluation tables).

Usage:
  python3 benches/refactor/compare_outputs.py BEFORE_BIN AFTER_BIN [--shared ../shared] [--work DIR]
          [--sets gqcnn-primesense,graspnet6dof-table,m2t2-table,cleargrasp-transparent]

Take BEFORE_BIN from the commit before the change (e.g. `git worktree add /tmp/before HEAD~1 &&
cargo build --release -p moma-cli --manifest-path /tmp/before/Cargo.toml`, or a copy of
target/release/moma made before editing). For every set both binaries run the same commands
(all on SIMULATED predictions, seeded):
  simulate; calibrate (ssra, gssa, lwlr, auto; with and without anchors); align every frame
  with --colormap --ply --json (and --realign anchors); metrics --json; grasp (suction and
  parallel, with -o: grasps.json, overlay.png, scene.ply; with and without --extrinsics and a
  --gripper-config); grasp-eval --json; eval --json (2 seeds).
Every file written and every stdout is then compared byte for byte, except wall times: calib.json
files are compared after dropping `created` (the date and the program version), and JSON on stdout
and in calib.json without the keys ending in `_ms` or `time_s`. Prints one line per difference and
exits 1 if there is any. Build both binaries the same way (e.g. both with the README's test
command, `cargo test --workspace --release --features moma-depth/onnx --no-run`): a workspace-wide
build can unify features that `cargo build -p moma-cli` does not. (The PNG encoder's deflate
backend, which made the compressed bytes differ with the same pixels, is fixed to zlib-rs by
moma-io since 2026-12-02; binaries built before that still differ in it.)
"""
import argparse
import filecmp
import json
import os
import subprocess
import sys
from pathlib import Path

EXTRINSICS = {"camera_to_base": [[0.0, -1.0, 0.0, 0.4], [-1.0, 0.0, 0.0, 0.1], [0.0, 0.0, -1.0, 0.9],
                                 [0.0, 0.0, 0.0, 1.0]]}
GRIPPER = {"stroke_m": 0.07, "finger_height_m": 0.015}


def run(bin_, args, out_dir, tag):
    """Runs `bin_ args`; stdout goes to out_dir/stdout/tag.txt (the exit code and stderr too)."""
    p = subprocess.run([bin_, *map(str, args)], capture_output=True, text=True, timeout=1800)
    d = out_dir / "stdout"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{tag}.txt").write_text(f"exit {p.returncode}\n{p.stdout}")
    if p.returncode != 0:
        (d / f"{tag}.stderr.txt").write_text(p.stderr)
    return p


def produce(bin_, shared, sets, out):
    out.mkdir(parents=True, exist_ok=True)
    (out / "extrinsics.json").write_text(json.dumps(EXTRINSICS))
    (out / "gripper.json").write_text(json.dumps(GRIPPER))
    for name in sets:
        s = shared / "data" / name
        o = out / name
        o.mkdir(parents=True, exist_ok=True)
        frames = sorted(p.name for p in (s / "frames").iterdir())
        run(bin_, ["simulate", "--set", s, "-o", o / "pred"], out, f"{name}-simulate")
        first = frames[0]
        cam = s / "camera.json"
        for method in ["ssra", "gssa", "lwlr", "auto"]:
            run(bin_, ["calibrate", "--pred", o / "pred" / f"{first}.npy", "--gt", s / "frames" / first / "depth.png",
                       "--camera", cam, "--method", method, "--seed", "3", "-o", o / f"calib-{method}.json", "--json"],
                out, f"{name}-calibrate-{method}")
        run(bin_, ["calibrate", "--pred", o / "pred" / f"{first}.npy", "--gt", s / "frames" / first / "depth.png",
                   "--camera", cam, "--anchors", "--anchors-rgb", s / "frames" / first / "rgb.png",
                   "-o", o / "calib-anchors.json", "--json"], out, f"{name}-calibrate-anchors")
        preds = [o / "pred" / f"{f}.npy" for f in frames[1:]]
        for method in ["ssra", "lwlr"]:
            run(bin_, ["align", "--calib", o / f"calib-{method}.json", "--pred", *preds, "-o", o / f"aligned-{method}",
                       "--colormap", "--ply", "--json"], out, f"{name}-align-{method}")
        if (o / "calib-anchors.json").is_file():
            f1 = frames[1]
            run(bin_, ["align", "--calib", o / "calib-anchors.json", "--pred", o / "pred" / f"{f1}.npy", "-o",
                       o / "aligned-realign", "--realign", "anchors", "--realign-rgb", s / "frames" / f1 / "rgb.png",
                       "--json"], out, f"{name}-align-realign")
        f1 = frames[1]
        run(bin_, ["metrics", "--pred", o / "aligned-ssra" / f"{f1}.depth.png", "--gt", s / "frames" / f1 / "depth.png",
                   "--json"], out, f"{name}-metrics")
        for gripper in ["suction", "parallel"]:
            base = ["grasp", "--calib", o / "calib-ssra.json", "--pred", o / "pred" / f"{f1}.npy", "--gripper", gripper,
                    "--top", "5", "--json"]
            run(bin_, [*base, "-o", o / f"grasp-{gripper}"], out, f"{name}-grasp-{gripper}")
            run(bin_, [*base, "--extrinsics", out / "extrinsics.json", "-o", o / f"grasp-{gripper}-base"], out,
                f"{name}-grasp-{gripper}-base")
            run(bin_, ["grasp", "--depth", s / "frames" / f1 / "depth.png", "--camera", cam, "--gripper", gripper,
                       "--top", "5", "--json", "-o", o / f"grasp-gt-{gripper}"], out, f"{name}-grasp-gt-{gripper}")
        run(bin_, ["grasp", "--depth", s / "frames" / f1 / "depth.png", "--camera", cam, "--gripper", "parallel",
                   "--gripper-config", out / "gripper.json", "--top", "3", "--json", "-o", o / "grasp-config"],
            out, f"{name}-grasp-config")
        run(bin_, ["grasp-eval", "--set", s, "--pred", o / "pred", "--seeds", "2", "--json"], out,
            f"{name}-grasp-eval")
        run(bin_, ["eval", "--set", s, "--pred", o / "pred", "--methods", "ssra,gssa,lwlr", "--seeds", "2", "--json"],
            out, f"{name}-eval")


TIMING_KEYS = ("_ms", "time_s")


def untimed(v):
    """`v` without wall-time fields (`*_ms`, `*time_s`): they differ between any two runs."""
    if isinstance(v, dict):
        return {k: untimed(x) for k, x in v.items() if not k.endswith(TIMING_KEYS)}
    if isinstance(v, list):
        return [untimed(x) for x in v]
    return v


def strip_created(path):
    d = json.loads(path.read_text())
    d.pop("created", None)
    return untimed(d)


def stdout_json(path):
    """A captured stdout: the exit line, then JSON (compared without timings) or text."""
    head, _, body = path.read_text().partition("\n")
    try:
        return head, untimed(json.loads(body))
    except ValueError:
        return head, body


def compare(a, b):
    diffs = []
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file()}
    for rel in sorted(files_a ^ files_b):
        diffs.append(f"only in {'before' if rel in files_a else 'after'}: {rel}")
    for rel in sorted(files_a & files_b):
        pa, pb = a / rel, b / rel
        if rel.name.startswith("calib") and rel.suffix == ".json":
            same = strip_created(pa) == strip_created(pb)
        elif rel.parts[0] == "stdout" and not rel.name.endswith(".stderr.txt"):
            same = stdout_json(pa) == stdout_json(pb)
        else:
            same = filecmp.cmp(pa, pb, shallow=False)
        if not same:
            diffs.append(f"differs: {rel}")
    return diffs, len(files_a & files_b)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--shared", default=str(Path(__file__).resolve().parents[3] / "shared"))
    ap.add_argument("--work", default="/tmp/moma-compare")
    ap.add_argument("--sets", default="gqcnn-primesense,graspnet6dof-table,m2t2-table,cleargrasp-transparent")
    a = ap.parse_args()
    shared, work = Path(a.shared), Path(a.work)
    sets = a.sets.split(",")
    # Both runs write the same paths relative to their own folder, so that stdout (which names
    # files) is comparable too: run each from inside its folder with relative outputs.
    for tag, bin_ in [("before", a.before), ("after", a.after)]:
        d = work / tag
        subprocess.run(["rm", "-rf", str(d)], check=True)
        d.mkdir(parents=True)
        cwd = os.getcwd()
        os.chdir(d)
        try:
            produce(os.path.abspath(os.path.join(cwd, bin_)) if not os.path.isabs(bin_) else bin_,
                    shared.resolve(), sets, Path("out"))
        finally:
            os.chdir(cwd)
    diffs, n = compare(work / "before" / "out", work / "after" / "out")
    for d in diffs:
        print(d)
    print(f"{n} files compared, {len(diffs)} difference(s)")
    sys.exit(1 if diffs else 0)


if __name__ == "__main__":
    main()
