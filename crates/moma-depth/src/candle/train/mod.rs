//! Fine-tuning Depth Anything V2 (docs/method.md §9): a differentiable training network ([`TrainNet`]),
//! LoRA adapters ([`LoraConfig`]) and losses ([`loss::loss`]).
//!
//! Random-weight reference models learn nothing meaningful: every loss computed on them is a test
//! of the machinery, not of a depth model's accuracy.

pub mod adapter;
mod attention;
mod elem;
pub mod finetune;
mod frozen;
mod gelu;
mod lora;
pub mod loss;
mod model;
mod norm;
mod resample;
#[cfg(test)]
mod testing;

pub use adapter::{
    ADAPTER_FORMAT, ADAPTER_FORMAT_V1, Adapter, fingerprint, merge_adapter, write_merged,
};
pub use finetune::{
    OPTIM_STATE_FORMAT, OptimSettings, Sample, Schedule, Trainer, clip_grad_norm, derive_seed,
    lr_factor, optim_state_path, seed_tag,
};
pub use lora::{LoraConfig, LoraTarget};
pub use loss::{LossKind, loss, loss_of, valid_indices};
pub use model::{LoraPart, NetOutput, ParamSource, TrainNet, metric_output};

use std::cell::Cell;

thread_local! {
    /// Set while a [`TrainNet`] with portable operations forced runs its forward on this thread.
    static PORTABLE: Cell<bool> = const { Cell::new(false) };
}

/// Whether this module's CPU kernels may run on `t`: a CPU tensor in f32 or f64, outside a
/// forward that forces the portable operations (what a GPU runs; see
/// [`TrainNet::set_portable_ops`]). Decided during the forward: each op's backward follows it.
pub(crate) fn cpu_kernels(t: &candle_core::Tensor) -> bool {
    t.device().is_cpu()
        && matches!(t.dtype(), candle_core::DType::F32 | candle_core::DType::F64)
        && !PORTABLE.with(Cell::get)
}

/// Forces (or not) the portable operations on this thread until dropped.
pub(crate) struct PortableScope(bool);

impl PortableScope {
    pub(crate) fn enter(on: bool) -> Self {
        Self(PORTABLE.with(|p| p.replace(on)))
    }
}

impl Drop for PortableScope {
    fn drop(&mut self) {
        PORTABLE.with(|p| p.set(self.0));
    }
}
