//! Small numerical kernels of the candle backend.

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// LayerNorm over the last dimension: `(x − mean) / sqrt(var + eps) · weight + bias`.
///
/// On the CPU a two-pass kernel (mean, then centred variance, in `f32`), parallel over rows:
/// `candle_nn::ops::layer_norm` uses `E[x²] − mean²`, which loses digits on the large-norm tokens
/// of real DINOv2 checkpoints. Other devices use `candle_nn::ops::layer_norm`.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn layer_norm(xs: &Tensor, weight: &Tensor, bias: &Tensor, eps: f32) -> Result<Tensor> {
    if xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32 {
        let xs = xs.contiguous()?;
        xs.apply_op3_no_bwd(weight, bias, &TwoPassLayerNorm { eps })
    } else {
        candle_nn::ops::layer_norm(xs, weight, bias, eps)
    }
}

struct TwoPassLayerNorm {
    eps: f32,
}

fn contiguous<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    let s = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s[a..b]),
        None => candle_core::bail!("layer-norm: operand must be contiguous"),
    }
}

impl CustomOp3 for TwoPassLayerNorm {
    fn name(&self) -> &'static str {
        "two-pass-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(s1, l1)?;
        let weight = contiguous(s2, l2)?;
        let bias = contiguous(s3, l3)?;
        let dim = l1.dims().last().copied().unwrap_or(1);
        if weight.len() != dim || bias.len() != dim {
            candle_core::bail!("layer-norm: weight/bias length {} vs dim {dim}", weight.len());
        }
        let mut dst = vec![0f32; src.len()];
        let eps = self.eps;
        dst.par_chunks_mut(dim).zip(src.par_chunks(dim)).for_each(|(d, s)| {
            let n = dim as f32;
            let mean = s.iter().sum::<f32>() / n;
            let var = s.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
            let inv = 1.0 / (var + eps).sqrt();
            for ((o, v), (w, b)) in d.iter_mut().zip(s).zip(weight.iter().zip(bias)) {
                *o = (v - mean) * inv * w + b;
            }
        });
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }
}
