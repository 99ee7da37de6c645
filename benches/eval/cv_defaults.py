"""Tables of issue 27's choice of the cross-validation defaults, from the JSON lines of
`cargo run --release -p moma-eval --example cv_defaults -- benches/eval/cv_defaults.json` (real
frames: REAL Depth Anything 3 predictions, per-frame protocol; simulated sets: SIMULATED
predictions, fixed-camera protocol). One row per configuration considered:
- real: the largest ratio, over the 3 frames and both scoring caps, of auto's AbsRel to the best
  of gssa/ssra/lwlr (target ≤ 1.05), and of ssra-local's to the better of ssra/lwlr (≤ 1.00), and
  auto's mean AbsRel;
- simulated: the largest ratio, over the 4 sets, of the masked MAE of auto, ssra-local and
  gssa-local to the first configuration's (today's defaults; target ≤ 1.02).

usage: python3 benches/eval/cv_defaults.py REAL.jsonl SIM.jsonl
"""
import collections
import json
import sys


def load(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def main(real_path, sim_path):
    real = collections.defaultdict(dict)  # (cap, frame) -> (label, method) -> rel
    for r in load(real_path):
        real[(r["cap"], r["frame"])][(r["label"], r["method"])] = r["rel"]
    sim = collections.defaultdict(lambda: collections.defaultdict(list))
    for r in load(sim_path):
        sim[r["set"]][(r["label"], r["method"])].append(r["mae"])
    labels = []
    for r in load(real_path):
        if r["label"] != "-" and r["label"] not in labels:
            labels.append(r["label"])
    base = labels[0]
    print("| configuration | real: auto / best ≤ 1.05 | real: ssra-local / min(ssra, lwlr) ≤ 1 "
          "| real: auto AbsRel (mean) | sim: auto / before | sim: ssra-local / before "
          "| sim: gssa-local / before |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for label in labels:
        ra, rs, mean = [], [], []
        for f, v in real.items():
            best = min(v[("-", m)] for m in ("gssa", "ssra", "lwlr"))
            ra.append(v[(label, "auto")] / best)
            rs.append(v[(label, "ssra-local")] / min(v[("-", "ssra")], v[("-", "lwlr")]))
            mean.append(v[(label, "auto")])
        cells = []
        for m in ("auto", "ssra-local", "gssa-local"):
            worst = max(
                (sum(v[(label, m)]) / len(v[(label, m)])) / (sum(v[(base, m)]) / len(v[(base, m)]))
                for v in sim.values()
            )
            cells.append(f"{worst:.3f}")
        print(f"| {label} | {max(ra):.3f} | {max(rs):.3f} | {sum(mean) / len(mean):.4f} | "
              + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
