//! Products with frozen (constant) weights whose backward computes only the input gradient.
//! candle's backward of `matmul` and `conv2d` always computes the gradient of both operands, so a
//! frozen weight costs a second product of the forward's size in every backward (the ViT's
//! linear layers, the DPT head's convolutions, the interpolation matrices). On CPU (f32/f64) the
//! product runs on an untracked copy of the input inside a custom op with an input-only
//! backward; elsewhere, or when the input carries no gradient, the plain operation runs.

use candle_core::{CpuStorage, CustomOp1, DType, Device, Layout, Result, Shape, Tensor};

type TensorFn = Box<dyn Fn(&Tensor) -> Result<Tensor> + Send + Sync>;

struct InputGradOnly {
    fwd: TensorFn,
    bwd: TensorFn,
}

impl CustomOp1 for InputGradOnly {
    fn name(&self) -> &'static str {
        "frozen-weight-product"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let Some((o0, o1)) = layout.contiguous_offsets() else {
            candle_core::bail!("frozen-weight product: input must be contiguous");
        };
        let x = match storage {
            CpuStorage::F32(v) => Tensor::from_slice(&v[o0..o1], layout.shape(), &Device::Cpu)?,
            CpuStorage::F64(v) => Tensor::from_slice(&v[o0..o1], layout.shape(), &Device::Cpu)?,
            _ => candle_core::bail!("frozen-weight product: f32 or f64 only"),
        };
        let y = (self.fwd)(&x)?;
        let shape = y.shape().clone();
        let flat = y.flatten_all()?;
        let out = match y.dtype() {
            DType::F32 => CpuStorage::F32(flat.to_vec1()?),
            DType::F64 => CpuStorage::F64(flat.to_vec1()?),
            other => candle_core::bail!("frozen-weight product: result in {other:?}"),
        };
        Ok((out, shape))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some((self.bwd)(grad_res)?))
    }
}

/// `fwd(x)`, with `bwd(dy)` as the gradient of `x` (the adjoint of the linear map `fwd`); no
/// gradient for the constants `fwd` closes over.
pub(crate) fn frozen(
    x: &Tensor,
    fwd: impl Fn(&Tensor) -> Result<Tensor> + Send + Sync + 'static,
    bwd: impl Fn(&Tensor) -> Result<Tensor> + Send + Sync + 'static,
) -> Result<Tensor> {
    let supported = x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64);
    if !supported || !x.track_op() {
        return fwd(x);
    }
    x.contiguous()?.apply_op1(InputGradOnly {
        fwd: Box::new(fwd),
        bwd: Box::new(bwd),
    })
}
