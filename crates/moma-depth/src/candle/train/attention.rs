//! Memory-light multi-head attention for training: the forward keeps no `T × T` attention
//! probabilities (B·H·T² values per block: 45 MB per ViT-S block at 518², kept for the backward
//! together with the scores, shifted scores and exponentials a composed softmax makes), and the
//! backward recomputes them from q and k (as FlashAttention does). The graph keeps only the
//! `(B, T, 3C)` qkv projection and the `(B, T, C)` output.
//!
//! CPU f32 runs the inference kernel (blocked, the scores of a block of query rows in cache); CPU
//! f64 (gradient checks) a plain loop; other devices use composed candle operations.

use candle_core::{CpuStorage, CustomOp1, D, Layout, Result, Shape, Tensor};

/// `softmax(scale · q kᵀ) v` per head on `qkv (B, T, 3C)` (PyTorch layout: `reshape(B, T, 3,
/// heads, C / heads)`) → `(B, T, C)`, differentiable in `qkv`.
///
/// # Errors
/// Shape errors, devices or dtypes without a kernel (callers use the composed path there).
pub(crate) fn attention(qkv: &Tensor, num_heads: usize, scale: f64) -> Result<Tensor> {
    qkv.contiguous()?
        .apply_op1(RecomputedAttention { num_heads, scale })
}

/// Whether [`attention`] has a kernel for `t`'s device and dtype.
pub(crate) fn supported(t: &Tensor) -> bool {
    t.device().is_cpu() && matches!(t.dtype(), candle_core::DType::F32 | candle_core::DType::F64)
}

struct RecomputedAttention {
    num_heads: usize,
    scale: f64,
}

impl RecomputedAttention {
    fn dims(&self, layout: &Layout) -> Result<(usize, usize, usize, usize)> {
        let (b, t, c3) = layout.shape().dims3()?;
        let h = self.num_heads;
        if !c3.is_multiple_of(3) || h == 0 || !(c3 / 3).is_multiple_of(h) {
            candle_core::bail!("attention: qkv {:?}, {h} heads", layout.dims());
        }
        Ok((b, t, c3 / 3, (c3 / 3) / h))
    }
}

/// Plain attention on one `(t, 3c)` slice (f64; small inputs in gradient checks).
fn attention_f64(qkv: &[f64], t: usize, c: usize, heads: usize, scale: f64, out: &mut [f64]) {
    let hd = c / heads;
    let c3 = 3 * c;
    let mut s = vec![0.0f64; t];
    for h in 0..heads {
        for i in 0..t {
            let q = &qkv[i * c3 + h * hd..i * c3 + (h + 1) * hd];
            let mut max = f64::NEG_INFINITY;
            for (j, sj) in s.iter_mut().enumerate() {
                let k = &qkv[j * c3 + c + h * hd..j * c3 + c + (h + 1) * hd];
                *sj = scale * q.iter().zip(k).map(|(a, b)| a * b).sum::<f64>();
                max = max.max(*sj);
            }
            let mut sum = 0.0;
            for sj in &mut s {
                *sj = (*sj - max).exp();
                sum += *sj;
            }
            let o = &mut out[i * c + h * hd..i * c + (h + 1) * hd];
            o.fill(0.0);
            for (j, sj) in s.iter().enumerate() {
                let v = &qkv[j * c3 + 2 * c + h * hd..j * c3 + 2 * c + (h + 1) * hd];
                for (od, vd) in o.iter_mut().zip(v) {
                    *od += sj / sum * vd;
                }
            }
        }
    }
}

impl CustomOp1 for RecomputedAttention {
    fn name(&self) -> &'static str {
        "recomputed-attention"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, t, c, _) = self.dims(layout)?;
        let Some((o0, o1)) = layout.contiguous_offsets() else {
            candle_core::bail!("attention: qkv must be contiguous");
        };
        let per = t * 3 * c;
        let shape = Shape::from_dims(&[b, t, c]);
        match storage {
            CpuStorage::F32(v) => {
                let v = &v[o0..o1];
                let mut out = Vec::with_capacity(b * t * c);
                for k in 0..b {
                    out.extend(crate::candle::ops::attention_cpu_f32(
                        &v[k * per..(k + 1) * per],
                        t,
                        self.num_heads,
                        self.scale as f32,
                    )?);
                }
                Ok((CpuStorage::F32(out), shape))
            }
            CpuStorage::F64(v) => {
                let v = &v[o0..o1];
                let mut out = vec![0.0f64; b * t * c];
                for k in 0..b {
                    attention_f64(
                        &v[k * per..(k + 1) * per],
                        t,
                        c,
                        self.num_heads,
                        self.scale,
                        &mut out[k * t * c..(k + 1) * t * c],
                    );
                }
                Ok((CpuStorage::F64(out), shape))
            }
            _ => candle_core::bail!("attention: f32 or f64 only"),
        }
    }

    /// With `P = softmax(s·q kᵀ)` recomputed and `dO` the output gradient: `dV = Pᵀ dO`,
    /// `dP = dO vᵀ`, `dS = P ⊙ (dP − rowsum(dO ⊙ O))`, `dQ = s·dS k`, `dK = s·dSᵀ q`.
    fn bwd(&self, arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let (b, t, c3) = arg.dims3()?;
        let h = self.num_heads;
        let hd = c3 / 3 / h;
        let qkv = arg
            .detach()
            .reshape((b, t, 3, h, hd))?
            .permute((2, 0, 3, 1, 4))?;
        let q = qkv.get(0)?.contiguous()?;
        let k = qkv.get(1)?.contiguous()?;
        let v = qkv.get(2)?.contiguous()?;
        let heads = |x: &Tensor| -> Result<Tensor> {
            x.reshape((b, t, h, hd))?.transpose(1, 2)?.contiguous()
        };
        let go = heads(grad_res)?;
        let o = heads(&res.detach())?;
        let p = candle_nn::ops::softmax_last_dim(&(q.matmul(&k.t()?)? * self.scale)?)?;
        let dv = p.t()?.matmul(&go)?;
        let dp = go.matmul(&v.t()?)?;
        let delta = (&go * &o)?.sum_keepdim(D::Minus1)?;
        let ds = (p * dp.broadcast_sub(&delta)?)?;
        let dq = (ds.matmul(&k)? * self.scale)?;
        let dk = (ds.t()?.matmul(&q)? * self.scale)?;
        let d = Tensor::stack(&[dq, dk, dv], 0)?; // (3, B, H, T, hd)
        Ok(Some(d.permute((1, 3, 0, 2, 4))?.reshape((b, t, c3))?))
    }
}
