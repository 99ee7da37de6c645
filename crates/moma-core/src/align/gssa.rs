//! placeholder: core work item
use serde::{Deserialize, Serialize};
/// Fitted global scale-shift: z = scale·ẑ + shift (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GssaModel {
    /// Scale, metres per unit ẑ.
    pub scale: f64,
    /// Shift, metres.
    pub shift_m: f64,
}
