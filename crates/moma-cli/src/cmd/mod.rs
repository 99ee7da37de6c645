//! One module per subcommand, plus the plumbing they share.

pub mod ablate;
pub mod align;
pub mod calibrate;
pub mod common;
pub mod demo;
pub mod eval;
pub mod grasp;
pub mod grasp_eval;
pub mod metrics;
pub mod predict;
pub mod simulate;
