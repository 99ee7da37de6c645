"""Random Depth Anything V2 ViT-B weights (relative head) for latency benchmarks, no download.

The tensor names and shapes of the official ViT-B checkpoint, derived from the ViT-S random-weight
reference in ../shared/reference/dav2 (embed 384 -> 768, MLP 1536 -> 3072, DPT out_channels
[48, 96, 192, 384] -> [96, 192, 384, 768], features 64 -> 128); values N(0, 0.02²), LayerNorm
gains 1, LayerScale 0.1, seed 0, float16 safetensors (97.5 M parameters, 195 MB). RANDOM
weights: for timing and memory only, never for depth. Without numpy, Python's own generator
draws the values (other values, the same shapes and scale; about 40 s).

    python benches/latency/random_vitb.py ../shared/reference/dav2/vits-rel.safetensors OUT.safetensors
"""
import json, struct, sys
try:
    import numpy as np
except ImportError:  # no numpy: Python's own generator (other values, same shapes and scale)
    np = None
src, dst = sys.argv[1], sys.argv[2]
f=open(src,'rb'); n=struct.unpack('<Q',f.read(8))[0]; h=json.loads(f.read(n))
enc={384:768,1152:2304,1536:3072}
oc={48:96,96:192,192:384,384:768}
def newshape(k,s):
    s=list(s)
    if k.startswith('pretrained.'):
        return [enc.get(d,d) if i>0 or k.endswith(('weight','bias','gamma')) or len(s)==1 else d for i,d in enumerate(s)] if 'pos_embed' not in k and 'cls_token' not in k and 'mask_token' not in k else s[:-1]+[768]
    if '.projects.' in k:
        return [oc[s[0]]]+([768]+s[2:] if len(s)>1 else [])
    if '.resize_layers.' in k:
        return [oc.get(d,d) if i<2 else d for i,d in enumerate(s)]
    if '_rn.' in k:
        return [128, oc[s[1]]]+s[2:]
    if '.refinenet' in k:
        return [128 if d==64 else d for d in s]
    if 'output_conv1' in k:
        return [64]+([128]+s[2:] if len(s)>1 else [])
    if 'output_conv2.0.weight' in k:
        return [32,64,3,3]
    return s
def f16_bytes(k, s):
    count = 1
    for d in s:
        count *= d
    if k.endswith('norm1.weight') or k.endswith('norm2.weight') or k=='pretrained.norm.weight':
        const = 1.0
    elif 'gamma' in k:
        const = 0.1
    else:
        const = None
    if np is not None:
        a = np.full(s, const, np.float16) if const is not None else (rng.standard_normal(s)*0.02).astype(np.float16)
        return a.tobytes()
    if const is not None:
        return struct.pack('<e', const) * count
    out = bytearray()
    for start in range(0, count, 1 << 16):
        n = min(1 << 16, count - start)
        out += struct.pack('<%de' % n, *(rng.gauss(0.0, 0.02) for _ in range(n)))
    return bytes(out)
if np is not None:
    rng=np.random.default_rng(0)
else:
    import random
    rng=random.Random(0)
hdr={}; blobs=[]; off=0
for k in sorted(x for x in h if x!='__metadata__'):
    s=newshape(k,h[k]['shape'])
    b=f16_bytes(k, s); hdr[k]={'dtype':'F16','shape':s,'data_offsets':[off,off+len(b)]}; off+=len(b); blobs.append(b)
hj=json.dumps(hdr).encode(); hj+=b' '*((8-len(hj)%8)%8)
tmp = dst + '.tmp'
with open(tmp,'wb') as o:
    o.write(struct.pack('<Q',len(hj))); o.write(hj); [o.write(b) for b in blobs]
import os
os.replace(tmp, dst)
print('params', off//2)
for k in ['pretrained.blocks.0.attn.qkv.weight','pretrained.pos_embed','depth_head.projects.3.weight','depth_head.scratch.layer1_rn.weight','depth_head.scratch.output_conv2.0.weight','pretrained.patch_embed.proj.weight']:
    print(k, hdr[k]['shape'])
