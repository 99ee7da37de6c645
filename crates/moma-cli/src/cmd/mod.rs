//! One module per subcommand, plus the plumbing they share.

pub mod ablate;
pub mod align;
pub mod calibrate;
pub mod common;
pub mod demo;
pub mod eval;
#[cfg(feature = "candle")]
pub mod finetune;
pub mod grasp;
pub mod grasp_eval;
#[cfg(feature = "candle")]
pub mod lora;
pub mod metrics;
pub mod predict;
pub mod ros2;
pub mod ros2_replay;
pub mod simulate;
