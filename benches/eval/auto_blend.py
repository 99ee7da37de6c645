"""Summarises `cargo run --example auto_blend` (SIMULATED predictions): per set, the masked MAE
(mm, mean over simulator and sampling seeds) of each of auto's candidates, of `auto`, and of each
blend of the candidates, with the change against the best single candidate.

    python3 benches/eval/auto_blend.py out/auto_blend.jsonl
"""
import json,sys,collections
rows=[json.loads(l) for l in open(sys.argv[1])]
by=collections.defaultdict(list)
for r in rows: by[r['set']].append(r)
for s,rs in by.items():
    names=rs[0]['names']
    import statistics as st
    mae={n:st.mean(r['maes'][i] for r in rs)*1000 for i,n in enumerate(names)}
    best=min(v for n,v in mae.items() if n!='auto')
    line=f"{s:24s} n={len(rs)} "+" ".join(f"{n}={v:.2f}" for n,v in mae.items())
    print(line)
    for b in rs[0]['blends']:
        v=st.mean(r['blends'][b] for r in rs)*1000
        print(f"    {b:12s} {v:.2f} ({(v/best-1)*100:+.1f}%)")
    print(f"    auto {(mae['auto']/best-1)*100:+.1f}%")
