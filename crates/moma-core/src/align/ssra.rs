//! placeholder: core work item
use serde::{Deserialize, Serialize};
/// SSRA settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct SsraConfig {
    /// Intrinsics used to report the canonical 7 parameters (else image centre and f = width).
    pub intrinsics: Option<crate::camera::Intrinsics>,
}
/// Fitted SSRA: z = ẑ(αu + βv + γ) + T3, plus the canonical (s, θ, φ, T3, cx, cy, f).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SsraModel {}
