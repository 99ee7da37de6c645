//! placeholder: core work item
use serde::{Deserialize, Serialize};
/// LWLR settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct LwlrConfig {}
/// Fitted LWLR.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LwlrModel {}
