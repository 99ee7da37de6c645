#!/usr/bin/env python3
"""int8 Depth Anything V2 for moma's ONNX Runtime backend: dynamic quantisation of an fp32 export.

Usage (the venv of `.ci/install-onnxruntime.sh --python`, plus `pip install onnx`):
  target-ort/venv/bin/python benches/onnx/quantize_int8.py MODEL.onnx [OUT.onnx] [--ops MatMul,Gemm]
then `moma predict --weights OUT.onnx ...` (for ONNX the file alone decides the precision).

What it does: ONNX Runtime's `quantize_dynamic`, int8 weights with one scale per output channel
(`per_channel=True`, symmetric QInt8) and activations quantised per tensor at run time
(DynamicQuantizeLinear → MatMulInteger, which ONNX Runtime runs with the CPU's VNNI dot products
where it has them). By default only the MatMul/Gemm nodes with a constant weight: the ViT's linear
layers (qkv, proj, MLP: 48 MatMulInteger in ViT-S), most of the FLOPs; the attention's QKᵀ and AV
products and the DPT head's convolutions stay fp32 (measured on the ViT-S random-weight reference:
max error 1.06 % of the output range; with the attention products 1.16 %, `--all-matmuls`; with
the convolutions 7.2 %, `--ops MatMul,Gemm,Conv`; docs/depth-model.md). The result is written atomically
(temporary file, then rename). The model is first shape-inferred and pre-processed
(`quant_pre_process`: constant folding and fusions that quantisation needs), as ORT recommends.
"""
import argparse
import os
import pathlib
import tempfile

from onnxruntime.quantization import QuantType, quantize_dynamic
from onnxruntime.quantization.shape_inference import quant_pre_process


def quantize(model, out, ops=("MatMul", "Gemm"), all_matmuls=False):
    """Writes the int8 version of the fp32 ONNX file `model` to `out` (temporary file, then rename)."""
    model, out = pathlib.Path(model), pathlib.Path(out)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        pre = pathlib.Path(tmp) / "pre.onnx"
        quant_pre_process(str(model), str(pre), skip_symbolic_shape=True)
        part = pathlib.Path(tmp) / "int8.onnx"
        quantize_dynamic(str(pre), str(part), weight_type=QuantType.QInt8, per_channel=True,
                         op_types_to_quantize=list(ops),
                         extra_options={"MatMulConstBOnly": not all_matmuls})
        os.replace(part, out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=pathlib.Path)
    ap.add_argument("out", type=pathlib.Path, nargs="?")
    ap.add_argument("--ops", default="MatMul,Gemm",
                    help="node types to quantise (comma-separated; e.g. MatMul,Gemm,Conv)")
    ap.add_argument("--all-matmuls", action="store_true",
                    help="also quantise the attention's activation × activation products")
    args = ap.parse_args()
    out = args.out or args.model.with_suffix(".int8.onnx")
    quantize(args.model, out, args.ops.split(","), args.all_matmuls)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB; {args.model} "
          f"{args.model.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
