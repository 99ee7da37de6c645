#!/usr/bin/env python3
"""Issue 22's target table from `moma grasp-eval --json` runs (docs/grasping.md, "Where issue 22's
targets stand").  SIMULATED predictions, PROXY scores: label every figure so.

    bash benches/grasp/targets.sh OUT [more grasp-eval flags]   # runs, then calls this script
    python3 benches/grasp/targets.py OUT [OUT2 ...]              # summarise existing runs

Each OUT holds `suction/s<K>.json` and `parallel/s<K>.json` (the `--json` output of one simulator
seed K) and `<gripper>/out<K>/sigma_coverage.json` (written by `-o`).  For each gripper and
(variant, grasp quality) the table gives, per set, top-1 successes / best of the candidates /
trials summed over the simulator seeds; the success rate as a share of the GT row's rate (the
planner on ground truth, σ = 0), averaged over the sets and its lowest set; the mean Brier score
of the rows and, in brackets, the mean of their base rates' (`brier_base_rate`: one constant
forecast at the achieved rate; `success_prob` carries information only below it).  Issue 22's targets, re-aligned with robust grasps: ≥ 85 % (suction) and ≥ 75 %
(parallel jaw) of GT on average, no set under 60 %; the GT row pooled ≥ 90 %.  Then the error
model's coverage: the rows (set × method × variant × region `all` / `masks`, pixels pooled over
the seeds) outside 55–80 % within ±1σ or under 90 % within ±2σ.

Standard library only.
"""

import glob
import json
import os
import sys
from collections import defaultdict

TARGETS = {"suction": 85.0, "parallel": 75.0}
SET_FLOOR = 60.0
GT_POOLED = 90.0


def load_rows(path):
    """The rows of one `--json` file (a list of objects), with a clear error otherwise."""
    try:
        with open(path, encoding="utf-8") as f:
            rows = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        sys.exit(f"{path}: not a grasp-eval --json output ({e})")
    if not isinstance(rows, list):
        sys.exit(f"{path}: expected a list of rows")
    return rows


def grasp_table(run):
    """Markdown lines of the success table of one run folder."""
    # (gripper, variant, quality, set) -> [successes, best of candidates, trials]
    sums = defaultdict(lambda: [0, 0, 0])
    briers = defaultdict(list)
    base_rates = defaultdict(list)
    # (gripper, variant, quality, set) -> [check successes, check grasps]
    checks = defaultdict(lambda: [0, 0])
    seeds = defaultdict(set)
    for gripper in ("suction", "parallel"):
        for path in sorted(glob.glob(os.path.join(run, gripper, "s*.json"))):
            seeds[gripper].add(os.path.basename(path))
            for r in load_rows(path):
                gt = r["method"] in ("gt", "GT")
                variant = "GT" if gt else r["variant"]
                quality = "nominal" if gt else r["grasp_quality"]
                key = (r["gripper"], variant, quality, r["set"])
                s = sums[key]
                s[0] += r["successes"]
                s[1] += r.get("best_of_candidates", 0)
                s[2] += r["trials"]
                if r.get("brier") is not None:
                    briers[key[:3]].append(r["brier"])
                if r.get("brier_base_rate") is not None:
                    base_rates[key[:3]].append(r["brier_base_rate"])
                c = r.get("calibration_frame_check")
                if c:
                    checks[key][0] += c["successes"]
                    checks[key][1] += c["grasps"]
    if not sums:
        sys.exit(f"{run}: no suction/s*.json or parallel/s*.json")
    sets = sorted({k[3] for k in sums})
    lines = [
        f"**{run}** (SIMULATED predictions, PROXY scores; simulator seeds: "
        + ", ".join(f"{g} {len(s)}" for g, s in sorted(seeds.items()))
        + "). Cells: top-1 successes / best of candidates / trials.",
        "",
        "| gripper | variant | grasps | " + " | ".join(sets) + " | % of GT (lowest set) | target | mean Brier (base rate) |",
        "|---|---|---|" + "---:|" * len(sets) + "---:|---:|---:|",
    ]
    for gripper in ("suction", "parallel"):
        rows = sorted({k[1:3] for k in sums if k[0] == gripper and k[1] != "GT"})
        for variant, quality in rows:
            cells, shares = [], []
            for name in sets:
                s = sums[(gripper, variant, quality, name)]
                g = sums[(gripper, "GT", "nominal", name)]
                if s[2] == 0:
                    cells.append("-")
                    continue
                cells.append(f"{s[0]} / {s[1]} / {s[2]}")
                if g[2] and g[0]:
                    shares.append(100.0 * (s[0] / s[2]) / (g[0] / g[2]))
            share = (
                f"{sum(shares) / len(shares):.1f} % ({min(shares):.1f} %)" if shares else "-"
            )
            target = ""
            if variant == "realign-anchors" and quality == "robust" and gripper in TARGETS:
                target = f"{TARGETS[gripper]:.0f} % ({SET_FLOOR:.0f} %)"
            b = briers[(gripper, variant, quality)]
            brier = f"{sum(b) / len(b):.3f}" if b else "-"
            base = base_rates[(gripper, variant, quality)]
            if b and base:
                # a success_prob that tells grasps apart scores under its rows' base rates
                brier += f" ({sum(base) / len(base):.3f})"
            lines.append(
                f"| {gripper} | {variant} | {quality} | " + " | ".join(cells)
                + f" | {share} | {target} | {brier} |"
            )
        gt = [sums[(gripper, "GT", "nominal", name)] for name in sets]
        if any(g[2] for g in gt):
            pooled = 100.0 * sum(g[0] for g in gt) / max(sum(g[2] for g in gt), 1)
            lines.append(
                f"| {gripper} | GT (σ = 0) | nominal | "
                + " | ".join(f"{g[0]} / {g[2]}" for g in gt)
                + f" | pooled {pooled:.1f} % | ≥ {GT_POOLED:.0f} % | |"
            )
    check_rows = sorted({k[:3] for k in checks})
    if check_rows:
        lines += [
            "",
            "Calibration frame's grasp check (`moma calibrate --grasp-check`: no mask, summed over"
            " the calibrations; grasps that hold / planned) beside the rate the row achieved.",
            "",
            "| gripper | variant | grasps | "
            + " | ".join(f"{n}: check | achieved" for n in sets)
            + " |",
            "|---|---|---|" + "---:|---:|" * len(sets),
        ]
        for gripper, variant, quality in check_rows:
            cells = []
            for name in sets:
                c = checks[(gripper, variant, quality, name)]
                s = sums[(gripper, variant, quality, name)]
                if c[1] == 0 or s[2] == 0:
                    cells.append("- | -")
                    continue
                cells.append(f"{c[0]} / {c[1]} ({c[0] / c[1]:.2f}) | {s[0] / s[2]:.2f}")
            lines.append(f"| {gripper} | {variant} | {quality} | " + " | ".join(cells) + " |")
    return lines


def coverage_table(run):
    """Markdown lines of the error model's coverage, pixels pooled over the seeds. Both
    grippers' runs of one seed write the same σ maps, so one gripper's files are read (suction
    where present)."""
    paths = sorted(glob.glob(os.path.join(run, "suction", "out*", "sigma_coverage.json")))
    if not paths:
        paths = sorted(glob.glob(os.path.join(run, "parallel", "out*", "sigma_coverage.json")))
    if not paths:
        return []
    sums = defaultdict(lambda: [0, 0.0, 0.0])
    for path in paths:
        for r in load_rows(path):
            if r["region"] == "edges":
                continue
            s = sums[(r["set"], r["method"], r["variant"], r["region"])]
            n = r["pixels"]
            s[0] += n
            s[1] += r["within_1sigma"] * n
            s[2] += r["within_2sigma"] * n
    lines = [
        "",
        "Error model: % of true errors within ±1σ / ±2σ (target 55–80 / ≥ 90), pixels pooled "
        "over the seeds; `!` marks a row outside the target.",
        "",
        "| set | method | variant | all pixels | inside the masks |",
        "|---|---|---|---:|---:|",
    ]
    outside = defaultdict(lambda: [0, 0])
    for name, method, variant in sorted({k[:3] for k in sums}):
        cells = []
        for region in ("all", "masks"):
            n, w1, w2 = sums[(name, method, variant, region)]
            if n == 0:
                cells.append("-")
                continue
            p1, p2 = 100.0 * w1 / n, 100.0 * w2 / n
            bad = p1 < 55.0 or p1 > 80.0 or p2 < 90.0
            outside[variant][0] += bad
            outside[variant][1] += 1
            cells.append(f"{'! ' if bad else ''}{p1:.1f} / {p2:.1f}")
        lines.append(f"| {name} | {method} | {variant} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(
        "Rows outside the target: "
        + ", ".join(f"{v} {o[0]} of {o[1]}" for v, o in sorted(outside.items()))
        + "."
    )
    return lines


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print(__doc__)
        return 0 if len(argv) >= 2 else 2
    for i, run in enumerate(argv[1:]):
        if not os.path.isdir(run):
            sys.exit(f"{run}: not a folder")
        if i:
            print()
        print("\n".join(grasp_table(run) + coverage_table(run)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
