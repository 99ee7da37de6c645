//! Fine-tuning Depth Anything V2 (issue 10): a differentiable training network ([`TrainNet`]),
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

pub use adapter::{Adapter, fingerprint, merge_adapter, write_merged};
pub use finetune::{
    OPTIM_STATE_FORMAT, OptimSettings, Sample, Schedule, Trainer, clip_grad_norm, derive_seed,
    lr_factor, optim_state_path, seed_tag,
};
pub use lora::{LoraConfig, LoraTarget};
pub use loss::{LossKind, loss, valid_indices};
pub use model::{LoraPart, ParamSource, TrainNet};
