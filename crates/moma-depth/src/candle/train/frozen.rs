//! Custom gradients on every device, and products with frozen (constant) weights whose backward
//! computes only the input gradient.
//!
//! [`attach`] runs a forward outside candle's autograd graph (on a detached input, so that none
//! of its intermediates is kept) and ties the result to the input with a given backward. It needs
//! no kernel of its own (the op only copies the finished result), so it works on the CPU, CUDA
//! and Metal alike: the GPU path of the trainer uses it where the CPU path has kernels
//! (the recomputed attention, the LayerNorm, the frozen-weight products).
//!
//! candle's backward of `matmul` and `conv2d` always computes the gradient of both operands, so a
//! frozen weight would cost a second product of the forward's size in every backward (the ViT's
//! linear layers, the DPT head's convolutions, the interpolation matrices), and the weight's
//! gradient would be held until the step ends: [`frozen`] attaches the input-only adjoint.

use std::sync::Mutex;

use candle_core::backend::BackendStorage;
use candle_core::{
    CpuStorage, CudaStorage, CustomOp1, Layout, MetalStorage, Result, Shape, Storage, Tensor,
};

/// `bwd(x, y, dy)`: the gradient of `x` given the forward's input, output and output gradient.
type BackwardFn = Box<dyn Fn(&Tensor, &Tensor, &Tensor) -> Result<Tensor> + Send + Sync>;

/// `x → y` for a `y` computed beforehand, with the gradient of `x` from `bwd`. The op takes `y`
/// out in its forward, so that the graph holds only `x` and the op's own copy of `y`.
struct Attached {
    y: Mutex<Option<Tensor>>,
    bwd: BackwardFn,
}

impl Attached {
    fn take(&self) -> Result<Tensor> {
        let mut y = self
            .y
            .lock()
            .map_err(|_| candle_core::Error::Msg("attached gradient: poisoned".into()))?;
        y.take()
            .ok_or_else(|| candle_core::Error::Msg("attached gradient: forward ran twice".into()))
    }
}

/// A copy of the finished result `y` (contiguous from offset 0: see [`attach`]).
fn copy_result<S: BackendStorage>(
    y: &Tensor,
    pick: impl FnOnce(&Storage) -> Option<&S>,
) -> Result<(S, Shape)> {
    let (storage, layout) = y.storage_and_layout();
    let Some(s) = pick(&storage) else {
        candle_core::bail!("attached gradient: result on another device");
    };
    Ok((s.try_clone(layout)?, layout.shape().clone()))
}

impl CustomOp1 for Attached {
    fn name(&self) -> &'static str {
        "attached-gradient"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
        copy_result(&self.take()?, |s| match s {
            Storage::Cpu(s) => Some(s),
            _ => None,
        })
    }

    fn cuda_fwd(&self, _: &CudaStorage, _: &Layout) -> Result<(CudaStorage, Shape)> {
        copy_result(&self.take()?, |s| match s {
            Storage::Cuda(s) => Some(s),
            _ => None,
        })
    }

    fn metal_fwd(&self, _: &MetalStorage, _: &Layout) -> Result<(MetalStorage, Shape)> {
        copy_result(&self.take()?, |s| match s {
            Storage::Metal(s) => Some(s),
            _ => None,
        })
    }

    fn bwd(&self, x: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some((self.bwd)(&x.detach(), &res.detach(), grad_res)?))
    }
}

/// `y` (computed from `x` off the graph, e.g. from `x.detach()`) as a function of `x` whose
/// gradient is `bwd(x, y, dy)`. The graph keeps `x` and the result only. When `x` carries no
/// gradient, `y` is returned as it is.
///
/// # Errors
/// `x` and `y` on different devices or of different dtypes; errors of the copy.
pub(crate) fn attach(
    x: &Tensor,
    y: Tensor,
    bwd: impl Fn(&Tensor, &Tensor, &Tensor) -> Result<Tensor> + Send + Sync + 'static,
) -> Result<Tensor> {
    if !x.track_op() {
        return Ok(y);
    }
    let y = y.detach();
    let y = if y.is_contiguous() && y.layout().start_offset() == 0 {
        y
    } else {
        y.copy()?
    };
    if x.dtype() != y.dtype() {
        candle_core::bail!(
            "attached gradient: input {:?}, result {:?}",
            x.dtype(),
            y.dtype()
        );
    }
    x.apply_op1(Attached {
        y: Mutex::new(Some(y)),
        bwd: Box::new(bwd),
    })
}

/// `fwd(x)`, with `bwd(dy)` as the gradient of `x` (the adjoint of the linear map `fwd`); no
/// gradient for the constants `fwd` closes over. On every device (see [`attach`]).
///
/// # Errors
/// Errors of `fwd`, and of `bwd` in the backward.
pub(crate) fn frozen(
    x: &Tensor,
    fwd: impl Fn(&Tensor) -> Result<Tensor>,
    bwd: impl Fn(&Tensor) -> Result<Tensor> + Send + Sync + 'static,
) -> Result<Tensor> {
    if !x.track_op() {
        return fwd(x);
    }
    attach(x, fwd(&x.detach().contiguous()?)?, move |_, _, g| bwd(g))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// `x³` computed off the graph with the attached backward `3x²·dy`: autograd through it equals
    /// central finite differences, also for a result that is not contiguous (a transpose, copied
    /// by `attach`), and the op keeps no reference to the off-graph result after its forward.
    #[test]
    fn attached_gradient_matches_central_finite_differences() {
        let (rows, cols) = (3, 4);
        let x0: Vec<f64> = (0..rows * cols).map(|i| 0.3 * i as f64 - 1.7).collect();
        let r = Tensor::from_vec(
            (0..rows * cols)
                .map(|i| 1.0 + 0.1 * i as f64)
                .collect::<Vec<_>>(),
            (cols, rows),
            &Device::Cpu,
        )
        .unwrap();
        let cube_t = |x: &Tensor| -> Tensor {
            // y = (x³)ᵀ off the graph; dx = 3x² ⊙ dyᵀ.
            let y = x.detach().powf(3.0).unwrap().t().unwrap();
            attach(x, y, |x, _, g| x.sqr()?.affine(3.0, 0.0)? * g.t()?).unwrap()
        };
        let g = crate::candle::train::testing::check_input_gradient(
            "attached x³ᵀ",
            cube_t,
            &x0,
            &[rows, cols],
            &r,
            crate::candle::train::testing::FdCheck {
                tol: 1e-7,
                ..crate::candle::train::testing::FdCheck::EVERY_ENTRY
            },
        );
        let want: Vec<f64> = (0..rows * cols)
            .map(|i| 3.0 * x0[i] * x0[i] * (1.0 + 0.1 * ((i % cols) * rows + i / cols) as f64))
            .collect();
        for (i, (g, w)) in g.iter().zip(&want).enumerate() {
            assert!(
                (g - w).abs() < 1e-12 * w.abs().max(1.0),
                "x[{i}]: {g} vs {w}"
            );
        }
        // Without a gradient to carry, the result is returned as it is (no op recorded).
        let plain = Tensor::from_slice(&x0, (rows, cols), &Device::Cpu).unwrap();
        assert!(!cube_t(&plain).track_op());
        // The off-graph result is taken by the forward: a second forward of the op fails.
        let x = Var::from_tensor(&plain).unwrap();
        let op = Attached {
            y: Mutex::new(Some(plain.clone())),
            bwd: Box::new(|_, _, g| Ok(g.clone())),
        };
        assert!(x.as_tensor().apply_op1_no_bwd(&op).is_ok());
        assert!(x.as_tensor().apply_op1_no_bwd(&op).is_err());
    }
}
