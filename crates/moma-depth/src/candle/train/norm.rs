//! LayerNorm over the last dimension with frozen weight and bias as one op (CPU f32 and f64)
//! with an exact input-only backward: the composed LayerNorm (mean, centring, variance, square
//! root, division, scale, shift) makes eight full-size temporaries in the forward and more in its
//! backward. Rows in parallel; two-pass variance, accumulated in f64.
//!
//! Backward, with `x̂ = (x − μ)·r`, `r = 1/√(var + ε)` and `ĝ = g ⊙ w`:
//! `dx = r · (ĝ − mean(ĝ) − x̂ · mean(ĝ ⊙ x̂))`.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, D, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::elem::Elem;

/// Mean and `1/√(var + ε)` of one row (two-pass variance).
fn stats<T: Elem>(row: &[T], eps: f64) -> (f64, f64) {
    let n = row.len() as f64;
    let mean = row.iter().map(|v| v.f()).sum::<f64>() / n;
    let var = row.iter().map(|v| (v.f() - mean).powi(2)).sum::<f64>() / n;
    (mean, 1.0 / (var + eps).sqrt())
}

struct LayerNorm {
    w: Vec<f64>,
    b: Vec<f64>,
    eps: f64,
}

impl LayerNorm {
    fn forward<T: Elem>(&self, x: &[T]) -> Vec<T> {
        let d = self.w.len();
        let mut y = vec![T::default(); x.len()];
        y.par_chunks_mut(d).zip(x.par_chunks(d)).for_each(|(y, x)| {
            let (mean, r) = stats(x, self.eps);
            for (((o, v), w), b) in y.iter_mut().zip(x).zip(&self.w).zip(&self.b) {
                *o = T::of((v.f() - mean) * r * w + b);
            }
        });
        y
    }

    fn backward<T: Elem>(&self, x: &[T], g: &[T]) -> Vec<T> {
        let d = self.w.len();
        let n = d as f64;
        let mut dx = vec![T::default(); x.len()];
        dx.par_chunks_mut(d)
            .zip(x.par_chunks(d).zip(g.par_chunks(d)))
            .for_each(|(dx, (x, g))| {
                let (mean, r) = stats(x, self.eps);
                let (mut sg, mut sgx) = (0.0, 0.0);
                for ((v, gv), w) in x.iter().zip(g).zip(&self.w) {
                    let gh = gv.f() * w;
                    sg += gh;
                    sgx += gh * (v.f() - mean) * r;
                }
                let (mg, mgx) = (sg / n, sgx / n);
                for (((o, v), gv), w) in dx.iter_mut().zip(x).zip(g).zip(&self.w) {
                    let xh = (v.f() - mean) * r;
                    *o = T::of(r * (gv.f() * w - mg - xh * mgx));
                }
            });
        dx
    }

    fn check(&self, layout: &Layout) -> Result<(usize, usize)> {
        let d = self.w.len();
        if layout.dims().last() != Some(&d) {
            candle_core::bail!("layer norm: input {:?}, weight ({d})", layout.dims());
        }
        match layout.contiguous_offsets() {
            Some(r) => Ok(r),
            None => candle_core::bail!("layer norm: input must be contiguous"),
        }
    }
}

impl CustomOp1 for LayerNorm {
    fn name(&self) -> &'static str {
        "layer-norm-frozen-affine"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (o0, o1) = self.check(layout)?;
        let y = match storage {
            CpuStorage::F32(v) => CpuStorage::F32(self.forward(&v[o0..o1])),
            CpuStorage::F64(v) => CpuStorage::F64(self.forward(&v[o0..o1])),
            _ => candle_core::bail!("layer norm: f32 or f64 only"),
        };
        Ok((y, layout.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let op = LayerNormBackward(LayerNorm {
            w: self.w.clone(),
            b: self.b.clone(),
            eps: self.eps,
        });
        let dx = arg
            .detach()
            .contiguous()?
            .apply_op2_no_bwd(&grad_res.contiguous()?, &op)?;
        Ok(Some(dx))
    }
}

/// `(x, dy) → dx` of [`LayerNorm`].
struct LayerNormBackward(LayerNorm);

impl CustomOp2 for LayerNormBackward {
    fn name(&self) -> &'static str {
        "layer-norm-frozen-affine-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (a0, a1) = self.0.check(l1)?;
        let (b0, b1) = self.0.check(l2)?;
        if l1.dims() != l2.dims() {
            candle_core::bail!(
                "layer norm backward: input {:?}, gradient {:?}",
                l1.dims(),
                l2.dims()
            );
        }
        let dx = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(g)) => {
                CpuStorage::F32(self.0.backward(&x[a0..a1], &g[b0..b1]))
            }
            (CpuStorage::F64(x), CpuStorage::F64(g)) => {
                CpuStorage::F64(self.0.backward(&x[a0..a1], &g[b0..b1]))
            }
            _ => candle_core::bail!("layer norm backward: f32 or f64 operands of one dtype"),
        };
        Ok((dx, l1.shape().clone()))
    }
}

/// Whether [`layer_norm`] applies: CPU f32/f64 input, and a weight and bias that carry no
/// gradient (trained ones take the composed path).
pub(crate) fn supported(x: &Tensor, w: &Tensor, b: &Tensor) -> bool {
    super::cpu_kernels(x) && !w.track_op() && !b.track_op()
}

/// `(x − mean) / √(var + eps) · w + b` over the last dimension, differentiable in `x`.
///
/// # Errors
/// Shape errors, an unsupported device or dtype (see [`supported`]).
pub(crate) fn layer_norm(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let op = LayerNorm {
        w: w.to_dtype(DType::F64)?.to_vec1()?,
        b: b.to_dtype(DType::F64)?.to_vec1()?,
        eps,
    };
    x.contiguous()?.apply_op1(op)
}

/// `((x − mean) / σ, σ)` over the last dimension, σ = √(var + eps) with the two-pass (biased)
/// variance; differentiable.
pub(crate) fn standardise(x: &Tensor, eps: f64) -> Result<(Tensor, Tensor)> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let sigma = (xc.sqr()?.mean_keepdim(D::Minus1)? + eps)?.sqrt()?;
    Ok((xc.broadcast_div(&sigma)?, sigma))
}

/// LayerNorm over the last dimension from differentiable candle operations (two-pass
/// variance): differentiable in `x`, `w` and `b` alike (a trained weight or bias takes this path).
///
/// # Errors
/// Shape errors.
pub(crate) fn layer_norm_composed(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    standardise(x, eps)?.0.broadcast_mul(w)?.broadcast_add(b)
}

/// [`layer_norm`] from candle operations on any device and dtype (frozen `w` and `b`): the
/// forward off the graph, the backward `dx = (g·w − mean(g·w) − x̂·mean(g·w·x̂)) / σ` recomputed
/// from `x`, so that the graph keeps only `x` and the output (what a GPU runs).
///
/// # Errors
/// Shape errors.
pub(crate) fn layer_norm_portable(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let y = layer_norm_composed(&x.detach(), w, b, eps)?;
    let w = w.detach();
    super::frozen::attach(x, y, move |x, _, g| {
        let (xhat, sigma) = standardise(x, eps)?;
        let gy = g.broadcast_mul(&w)?;
        let m1 = gy.mean_keepdim(D::Minus1)?;
        let m2 = (&gy * &xhat)?.mean_keepdim(D::Minus1)?;
        (gy.broadcast_sub(&m1)? - xhat.broadcast_mul(&m2)?)?.broadcast_div(&sigma)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::candle::train::testing::{
        FdCheck, check_input_gradient, input_gradient, max_abs_diff,
    };
    use candle_core::{D, Device};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(n: usize, seed: u64, lo: f64, hi: f64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.random_range(lo..hi)).collect()
    }

    fn composed(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Tensor {
        let mean = x.mean_keepdim(D::Minus1).unwrap();
        let xc = x.broadcast_sub(&mean).unwrap();
        let var = xc.sqr().unwrap().mean_keepdim(D::Minus1).unwrap();
        xc.broadcast_div(&(var + eps).unwrap().sqrt().unwrap())
            .unwrap()
            .broadcast_mul(w)
            .unwrap()
            .broadcast_add(b)
            .unwrap()
    }

    /// A LayerNorm case: 3 rows of 7, weight, bias, the output weights `r` of `Σ LN(x) ⊙ r`, and
    /// an input whose rows are offset by large values (DINOv2's large-norm tokens).
    struct Case {
        eps: f64,
        w: Tensor,
        b: Tensor,
        r: Tensor,
        x0: Vec<f64>,
        shape: [usize; 3],
    }

    fn case() -> Case {
        let (rows, d) = (3, 7);
        let dev = Device::Cpu;
        Case {
            eps: 1e-6,
            w: Tensor::from_vec(random(d, 1, 0.5, 1.5), d, &dev).unwrap(),
            b: Tensor::from_vec(random(d, 2, -1.0, 1.0), d, &dev).unwrap(),
            r: Tensor::from_vec(random(rows * d, 3, -1.0, 1.0), (1, rows, d), &dev).unwrap(),
            x0: random(rows * d, 4, -2.0, 2.0)
                .iter()
                .enumerate()
                .map(|(i, v)| v + 30.0 * (i / d) as f64)
                .collect(),
            shape: [1, rows, d],
        }
    }

    /// Forward equals the composed LayerNorm; the input gradient of `Σ LN(x) ⊙ r` equals central
    /// finite differences (every entry) and the composed op's gradient, in f64.
    #[test]
    fn layer_norm_matches_composed_and_central_finite_differences_in_f64() {
        let Case {
            eps,
            w,
            b,
            r,
            x0,
            shape,
        } = case();
        let x = Tensor::from_slice(&x0, &shape[..], &Device::Cpu).unwrap();
        assert!(supported(&x, &w, &b));
        let diff = max_abs_diff(
            &layer_norm(&x, &w, &b, eps).unwrap(),
            &composed(&x, &w, &b, eps),
        );
        assert!(
            diff < 1e-12,
            "forward differs from the composed LayerNorm by {diff}"
        );
        let gc = input_gradient(|x| composed(x, &w, &b, eps), &x0, &shape, &r);
        let g = check_input_gradient(
            "layer norm",
            |x| layer_norm(x, &w, &b, eps).unwrap(),
            &x0,
            &shape,
            &r,
            FdCheck::EVERY_ENTRY,
        );
        for (i, (g, gc)) in g.iter().zip(&gc).enumerate() {
            assert!((g - gc).abs() < 1e-10, "x[{i}]: {g} vs composed {gc}");
        }
    }

    /// The portable LayerNorm (candle operations with an attached backward, what a GPU runs):
    /// forward and input gradient equal to the kernel's, the gradient also against central
    /// finite differences, in f64.
    #[test]
    fn portable_layer_norm_matches_the_kernel_and_central_finite_differences_in_f64() {
        let Case {
            eps,
            w,
            b,
            r,
            x0,
            shape,
        } = case();
        let x = Tensor::from_slice(&x0, &shape[..], &Device::Cpu).unwrap();
        let diff = max_abs_diff(
            &layer_norm(&x, &w, &b, eps).unwrap(),
            &layer_norm_portable(&x, &w, &b, eps).unwrap(),
        );
        assert!(diff < 1e-12, "forward differs from the kernel by {diff}");
        let g_portable = check_input_gradient(
            "portable layer norm",
            |x| layer_norm_portable(x, &w, &b, eps).unwrap(),
            &x0,
            &shape,
            &r,
            FdCheck::EVERY_ENTRY,
        );
        let g_kernel = input_gradient(|x| layer_norm(x, &w, &b, eps).unwrap(), &x0, &shape, &r);
        for (i, (p, k)) in g_portable.iter().zip(&g_kernel).enumerate() {
            assert!(
                (p - k).abs() < 1e-9 * k.abs().max(1.0),
                "x[{i}]: {p} vs kernel {k}"
            );
        }
    }
}

#[cfg(test)]
mod f32_tests {
    use super::*;
    use candle_core::{D, Device};

    /// The f32 op against the f64 composed LayerNorm: f32 round-off only.
    #[test]
    fn f32_forward_is_f64_accurate() {
        let (rows, d) = (5, 64);
        let dev = Device::Cpu;
        let x64: Vec<f64> = (0..rows * d)
            .map(|i| ((i * 7919 % 1000) as f64 / 500.0 - 1.0) + 30.0 * (i / d) as f64)
            .collect();
        let w64: Vec<f64> = (0..d).map(|i| 0.5 + (i % 7) as f64 / 7.0).collect();
        let b64: Vec<f64> = (0..d).map(|i| (i % 5) as f64 / 5.0 - 0.4).collect();
        let x = Tensor::from_vec(x64.clone(), (1, rows, d), &dev).unwrap();
        let w = Tensor::from_vec(w64, d, &dev).unwrap();
        let b = Tensor::from_vec(b64, d, &dev).unwrap();
        let mean = x.mean_keepdim(D::Minus1).unwrap();
        let xc = x.broadcast_sub(&mean).unwrap();
        let var = xc.sqr().unwrap().mean_keepdim(D::Minus1).unwrap();
        let want: Vec<f64> = xc
            .broadcast_div(&(var + 1e-6).unwrap().sqrt().unwrap())
            .unwrap()
            .broadcast_mul(&w)
            .unwrap()
            .broadcast_add(&b)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let x32 = x.to_dtype(DType::F32).unwrap();
        let got: Vec<f32> = layer_norm(
            &x32,
            &w.to_dtype(DType::F32).unwrap(),
            &b.to_dtype(DType::F32).unwrap(),
            1e-6,
        )
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!(
                (f64::from(*g) - w).abs() < 1e-5 * (1.0 + w.abs()),
                "y[{i}] = {g} vs {w}"
            );
        }
    }
}
