#!/usr/bin/env python3
"""Scores selection rules for `auto` (issue 12, item 1) on the output of the `auto_rules` example.

SIMULATED predictions only.  Each input line holds, for one (set, simulator seed, sampling seed),
every candidate's cross-validated squared errors on the 100 calibration samples (target units,
as `auto` computes them), the masked MAE it reaches on the other frames, and (for the bounds
below) its MAE on the calibration frame itself.  A rule picks one candidate per line; the table
gives its MAE per set (mean over simulator and sampling seeds) against the best single method's
mean, and in how many of the (set, simulator seed) cells it is within 3 % of that cell's best.

    MOMA_SHARED_DIR=../shared cargo run --release -p moma-eval --example auto_rules -- 10 10 > rules.jsonl
    python3 benches/eval/auto_rules.py rules.jsonl

The last two rows are not usable rules but bounds: they choose with the dense ground truth of the
calibration frame (inside its masks / every valid pixel), which `auto` does not see.  A second
table scores blends of the candidates (their aligned maps averaged with weights from the CV
errors) instead of a choice, when the input has them.
"""

import json
import math
import statistics
import sys

ORDER = ["gssa", "ssra", "gssa-local", "ssra-local", "lwlr"]  # auto's order, simplest first
SETS = ["gqcnn-primesense", "graspnet6dof-table", "m2t2-table", "cleargrasp-transparent"]
mean = statistics.fmean


def one_se(k):
    """The k-standard-error rule on paired losses, as `one_standard_error_choice` (k = 1)."""

    def rule(c):
        losses = [x["cv_sq"] for x in c]
        means = [mean(l) for l in losses]
        best = min(range(len(losses)), key=lambda i: (means[i], i))
        for i in range(best + 1):
            d = [a - b for a, b in zip(losses[i], losses[best])]
            md, n = mean(d), len(d)
            var = sum((x - md) ** 2 for x in d) / max(n - 1, 1)
            if md <= k * math.sqrt(var / n):
                return i
        return best

    return rule


def lowest(stat):
    return lambda c: min(range(len(c)), key=lambda i: stat(c[i]))


RULES = {
    "one-SE (auto)": one_se(1.0),
    "0.5 SE": one_se(0.5),
    "2 SE": one_se(2.0),
    "lowest CV mean square": lowest(lambda x: mean(x["cv_sq"])),
    "lowest CV median square": lowest(lambda x: statistics.median(x["cv_sq"])),
    "lowest CV mean absolute": lowest(lambda x: mean(math.sqrt(v) for v in x["cv_sq"])),
    **{f"always {m}": (lambda m: lambda c: ORDER.index(m))(m) for m in ORDER},
    "bound: calibration frame, masks": lowest(lambda x: x["calib_mask_mae_m"]),
    "bound: calibration frame, all pixels": lowest(lambda x: x["calib_whole_mae_m"]),
}


def main():
    rows = [json.loads(l) for l in open(sys.argv[1])]
    for r in rows:
        assert [x["method"] for x in r["candidates"]] == ORDER
    sims = sorted({r["sim_seed"] for r in rows})
    print(f"SIMULATED predictions; {len(sims)} simulator seeds; MAE mm (change vs the best single "
          "method on the set)\n")
    table(rows, sims, "rule", {name: (lambda rule: lambda r: r["candidates"][rule(r["candidates"])]["mae_m"])(rule)
                               for name, rule in RULES.items()})
    if "blends" not in rows[0]:
        return
    print("\nBlends instead of a choice (same cells):\n")
    table(rows, sims, "blend", {name: (lambda name: lambda r: r["blends"][name]["mae_m"])(name)
                                for name in rows[0]["blends"]})


def table(rows, sims, what, pickers):
    """One markdown row per picker (line -> masked MAE, metres): the MAE per set (mean over
    simulator and sampling seeds) against the best single method's, and the (set, simulator
    seed) cells within 3 % of that cell's best method."""
    print(f"| {what} | " + " | ".join(SETS) + f" | cells within 3 % (of {len(SETS) * len(sims)}) |")
    print("|---|" + "---|" * (len(SETS) + 1))
    for name, pick in pickers.items():
        cells, ok = [], 0
        for s in SETS:
            got, per_method = [], []
            for sim in sims:
                lines = [r for r in rows if r["set"] == s and r["sim_seed"] == sim]
                p = mean(pick(r) for r in lines)
                m = [mean(r["candidates"][j]["mae_m"] for r in lines) for j in range(len(ORDER))]
                ok += p <= 1.03 * min(m)
                got.append(p)
                per_method.append(m)
            a = mean(got)
            b = min(mean(m[j] for m in per_method) for j in range(len(ORDER)))
            cells.append(f"{1e3 * a:.2f} ({100 * (a / b - 1):+.1f} %)")
        print(f"| {name} | " + " | ".join(cells) + f" | {ok} |")

if __name__ == "__main__":
    main()
