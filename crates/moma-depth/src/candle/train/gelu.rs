//! Exact GELU, `0.5·x·(1 + erf(x/√2))`, as one op with its backward `g·(Φ(x) + x·φ(x))` (CPU):
//! f32 on the vectorised erf/exp of the inference kernels, in parallel (candle's `gelu_erf` calls
//! libm's scalar `erff` in the forward and again, with further temporaries, in its backward);
//! f64 with libm's `erf`/`exp`.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};

const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

struct Gelu;

fn slice<'a, T>(v: &'a [T], l: &Layout) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("gelu: operands must be contiguous"),
    }
}

impl CustomOp1 for Gelu {
    fn name(&self) -> &'static str {
        "gelu-erf"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let y = match storage {
            CpuStorage::F32(v) => {
                let mut y = slice(v, layout)?.to_vec();
                crate::candle::ops::gelu_f32_in_place(&mut y);
                CpuStorage::F32(y)
            }
            CpuStorage::F64(v) => CpuStorage::F64(
                slice(v, layout)?
                    .iter()
                    .map(|&x| 0.5 * x * (1.0 + libm::erf(x * std::f64::consts::FRAC_1_SQRT_2)))
                    .collect(),
            ),
            _ => candle_core::bail!("gelu: f32 or f64 only"),
        };
        Ok((y, layout.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let dx = arg
            .detach()
            .contiguous()?
            .apply_op2_no_bwd(&grad_res.contiguous()?, &GeluBackward)?;
        Ok(Some(dx))
    }
}

/// `(x, dy) → dy · GELU'(x)`.
struct GeluBackward;

impl CustomOp2 for GeluBackward {
    fn name(&self) -> &'static str {
        "gelu-erf-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        if l1.dims() != l2.dims() {
            candle_core::bail!(
                "gelu backward: input {:?}, gradient {:?}",
                l1.dims(),
                l2.dims()
            );
        }
        let dx = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(g)) => {
                let mut d = slice(g, l2)?.to_vec();
                crate::candle::ops::gelu_grad_f32_in_place(slice(x, l1)?, &mut d);
                CpuStorage::F32(d)
            }
            (CpuStorage::F64(x), CpuStorage::F64(g)) => CpuStorage::F64(
                slice(x, l1)?
                    .iter()
                    .zip(slice(g, l2)?)
                    .map(|(&x, &g)| {
                        let cdf = 0.5 * (1.0 + libm::erf(x * std::f64::consts::FRAC_1_SQRT_2));
                        g * (cdf + x * INV_SQRT_2PI * (-0.5 * x * x).exp())
                    })
                    .collect(),
            ),
            _ => candle_core::bail!("gelu backward: f32 or f64 operands of one dtype"),
        };
        Ok((dx, l1.shape().clone()))
    }
}

/// Exact GELU, differentiable: the op above on CPU f32/f64, candle's `gelu_erf` elsewhere.
///
/// # Errors
/// Shape errors.
pub(crate) fn gelu_erf(x: &Tensor) -> Result<Tensor> {
    if super::cpu_kernels(x) {
        x.contiguous()?.apply_op1(Gelu)
    } else {
        x.gelu_erf()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};

    fn grad(x: &Var, r: &Tensor, f: impl Fn(&Tensor) -> Tensor) -> Vec<f64> {
        let l = (f(x.as_tensor()) * r).unwrap().sum_all().unwrap();
        let g = l.backward().unwrap();
        g.get(x.as_tensor())
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_vec1()
            .unwrap()
    }

    /// f64: forward equals candle's `gelu_erf`, the gradient central finite differences; f32:
    /// forward and gradient equal candle's `gelu_erf` and its backward (erf approximations
    /// differ by ≤ 1e-6).
    #[test]
    fn gelu_matches_candle_and_central_finite_differences() {
        let dev = Device::Cpu;
        let xs: Vec<f64> = (0..41).map(|i| -6.0 + 0.3 * i as f64).collect();
        let r: Vec<f64> = (0..41).map(|i| 1.0 + 0.05 * i as f64).collect();
        let x = Var::from_tensor(&Tensor::from_slice(&xs, 41, &dev).unwrap()).unwrap();
        let rt = Tensor::from_slice(&r, 41, &dev).unwrap();
        let y: Vec<f64> = gelu_erf(x.as_tensor()).unwrap().to_vec1().unwrap();
        let want: Vec<f64> = x.as_tensor().gelu_erf().unwrap().to_vec1().unwrap();
        for (a, b) in y.iter().zip(&want) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        let g = grad(&x, &rt, |t| gelu_erf(t).unwrap());
        let eps = 1e-6;
        for (i, &xi) in xs.iter().enumerate() {
            let f = |v: f64| -> f64 {
                let t = Tensor::from_slice(&[v], 1, &dev).unwrap();
                gelu_erf(&t).unwrap().to_vec1::<f64>().unwrap()[0] * r[i]
            };
            let fd = (f(xi + eps) - f(xi - eps)) / (2.0 * eps);
            // Floor 1e-3 on the scale: at x = −6 both are ~4e-8 and `1 + erf` has cancelled.
            let rel = (fd - g[i]).abs() / fd.abs().max(g[i].abs()).max(1e-3);
            assert!(
                rel < 1e-6,
                "x = {xi}: autograd {} vs finite difference {fd}",
                g[i]
            );
        }
        let x32 = Var::from_tensor(&x.as_tensor().to_dtype(DType::F32).unwrap()).unwrap();
        let r32 = rt.to_dtype(DType::F32).unwrap();
        let g32 = grad(&x32, &r32, |t| gelu_erf(t).unwrap());
        let want32 = grad(&x32, &r32, |t| t.gelu_erf().unwrap());
        for (i, (a, b)) in g32.iter().zip(&want32).enumerate() {
            assert!(
                (a - b).abs() < 1e-5 * (1.0 + b.abs()),
                "x = {}: {a} vs candle {b}",
                xs[i]
            );
        }
    }
}
